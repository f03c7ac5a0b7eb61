"""``depthnerf train``: train a preset (baseline with ``--depth none``, depth-aware otherwise).

Any config field can be overridden with ``--section.field VALUE`` (e.g. ``--model.coarse.d_hidden 256``,
``--schedule.lr 2e-4``); ``--print-config`` prints the resolved config as JSON and exits. ``--config FILE`` reads
settings from a JSON file (a run's ``config.json``, a ``--print-config`` output, or a file holding only the fields
that differ): the config is built in layers, the preset (``--preset``, else the file's ``preset``, else
:data:`DEFAULT_PRESET`), then the file, then the named flags, then the ``--section.field`` overrides.

Multi-GPU / multi-node: launch the same command with ``torchrun --nproc_per_node=N -m depthnerf train ...``.

``--resume`` continues the run in ``--out`` from its last checkpoint, or starts it if there is none (a cluster
that preempts jobs reissues the same command); one line on stderr says which. On resume the run's own
``config.json`` is used: flags that agree with it are accepted, flags that change what is trained are refused
(see :data:`CHANGEABLE_ON_RESUME` for what may change), and ``--data`` may point at the same data moved elsewhere.

SIGTERM (a cluster about to preempt the job) or Ctrl+C writes a checkpoint at the current step, prints one line
on stderr with the exact command that resumes it (:func:`resume_command`) and exits with 143 / 130
(:mod:`depthnerf.train.stop`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shlex
import sys
from pathlib import Path
from typing import Any

from depthnerf.config_io import apply_overrides, differences, to_dict
from depthnerf.data.records import in_dataset
from depthnerf.depth.bundled import shipped_nets_text
from depthnerf.depth.estimators import ESTIMATORS
from depthnerf.errors import DepthnerfError, launch_rank, refusal
from depthnerf.files import read_json_object
from depthnerf.train.config import PRESETS, TrainConfig, check_config, from_dict_config, preset, with_prior

ACCEPTS_OVERRIDES = True

CHANGEABLE_ON_RESUME = ("schedule.max_steps", "schedule.step_shape", "data.root", "data.num_workers",
                        "data.view_store", "log.checkpoint_every", "log.keep_last", "log.log_every")
"""Config fields a ``--resume`` may change: where the data lives and how long/how observably to train, never
what is trained (the batches, model, prior and schedule of the steps already taken)."""

DEFAULT_PRESET = "cpu-cars"
"""Preset used when ``--preset`` is not given on a new run."""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--preset", choices=sorted(PRESETS), help=f"named preset (default {DEFAULT_PRESET})")
    p.add_argument("--config", metavar="FILE",
                   help="settings from a JSON file on top of the preset (a run's config.json, a --print-config "
                        "output, or only the fields that differ); the flags apply on top of it")
    p.add_argument("--data", help="dataset root (SRN layout); default: the preset's; stored resolved to an "
                                  "absolute path; on --resume it may point at the run's data moved elsewhere")
    p.add_argument("--out", help="run folder (config, metrics.jsonl, TensorBoard events, checkpoints/); not the "
                                 "dataset or one of its split folders")
    p.add_argument("--depth", choices=ESTIMATORS,
                   help="depth prior: none = pixelNeRF baseline; default: the preset's")
    p.add_argument("--depth-checkpoint",
                   help="depth estimator weights: hub id or local dir (depth-anything-v2), a shipped net's name "
                        f"(bundled: {shipped_nets_text()}) or a weights file")
    p.add_argument("--max-steps", type=int, help="total optimisation steps")
    p.add_argument("--checkpoint-every", type=int, help="steps between checkpoints")
    p.add_argument("--seed", type=int, help="run seed")
    p.add_argument("--init-from", metavar="CHECKPOINT",
                   help="warm start: a new run's network weights from this checkpoint (shipped name, path or "
                        "hf://OWNER/REPO; same "
                        "model config and prior); step, optimiser and schedule start fresh")
    p.add_argument("--resume", action="store_true",
                   help="continue the run in --out from its last checkpoint (or start it when it has none; "
                        "stderr says which); flags contradicting the run's config are refused")
    p.add_argument("--device", default="auto", help="auto (CUDA if available), cpu, cuda or cuda:N")
    p.add_argument("--deterministic", action="store_true",
                   help="deterministic algorithms (exact resume and same-seed runs on CUDA too; slower there)")
    how = p.add_mutually_exclusive_group()
    how.add_argument("--compile", action="store_true",
                     help="run the fields' MLPs through torch.compile (fuses their element-wise work: fewer kernel "
                          "launches on CUDA; compiles for a minute or more first; same results up to float rounding)")
    how.add_argument("--compile-step", action="store_true",
                     help="run the whole loss (encoder, render, loss terms, forward and backward) as one "
                          "torch.compile graph, replayed as CUDA graphs on CUDA (compiles for minutes first; same "
                          "results up to float rounding)")
    p.add_argument("--print-config", action="store_true", help="print the resolved config as JSON and exit")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--strict", action="store_true",
                   help="a problem in an optional part of the data (depth/, mask/, mesh.ply) is an error")


def _apply_flags(cfg: TrainConfig, args: argparse.Namespace) -> TrainConfig:
    """--depth -> named flags -> --section.field overrides, on top of ``cfg``."""
    if args.depth is not None or args.depth_checkpoint is not None:
        prior = cfg.prior.override(args.depth, args.depth_checkpoint)
        cfg = with_prior(cfg, prior.estimator, prior.checkpoint)
    if args.data is not None:
        cfg = dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, root=str(Path(args.data).resolve())))
    if args.seed is not None:
        cfg = dataclasses.replace(cfg, seed=args.seed)
    if args.init_from is not None:
        cfg = dataclasses.replace(cfg, init_from=args.init_from)
    sched, log = cfg.schedule, cfg.log
    if args.max_steps is not None:
        sched = dataclasses.replace(sched, max_steps=args.max_steps)
    if args.checkpoint_every is not None:
        log = dataclasses.replace(log, checkpoint_every=args.checkpoint_every)
    cfg = dataclasses.replace(cfg, schedule=sched, log=log)
    return apply_overrides(cfg, args.overrides)


def config_changes(old: TrainConfig, new: TrainConfig) -> dict[str, tuple[Any, Any]]:
    """Dotted config paths whose values differ: ``{path: (old, new)}``."""
    return differences(json.loads(json.dumps(to_dict(old))), json.loads(json.dumps(to_dict(new))))


def _merged(base: dict[str, Any], top: dict[str, Any]) -> dict[str, Any]:
    """``base`` with ``top``'s values laid over it, section by section (a mapping in both merges key by key)."""
    out = dict(base)
    for key, value in top.items():
        out[key] = _merged(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def _with_config_file(cfg: TrainConfig, args: argparse.Namespace) -> TrainConfig:
    """``cfg`` with ``--config FILE``'s settings laid over it (unknown fields and wrong types name the file)."""
    if args.config is None:
        return cfg
    path = Path(args.config)
    data = read_json_object(path, "--config file")
    return from_dict_config(_merged(json.loads(json.dumps(to_dict(cfg))), data), where=str(path))


def _resume_config(args: argparse.Namespace, path: Path) -> TrainConfig:
    stored = from_dict_config(read_json_object(path, "run config"), where=str(path))
    if args.preset is not None and args.preset != stored.preset:
        raise DepthnerfError(f"--resume: {path} is a {stored.preset} run, not --preset {args.preset}; drop the "
                             "flag or choose another --out")
    cfg = _apply_flags(_with_config_file(stored, args), args)
    changes = config_changes(stored, cfg)
    refused = {k: v for k, v in changes.items() if k not in CHANGEABLE_ON_RESUME}
    if refused:
        said = ", ".join(f"{k} {json.dumps(o)} -> {json.dumps(n)}" for k, (o, n) in list(refused.items())[:4])
        which = "the flags" if args.config is None else f"the flags and --config {args.config}"
        raise DepthnerfError(f"--resume: {which} contradict the run's config {path} ({said}); drop them to "
                             "resume, or choose another --out for a new run")
    if "data.root" in changes:
        old, new = changes["data.root"]
        print(f"resume: reading the data from --data {new} (the run's config said {old})", file=sys.stderr)
    return check_config(_absolute_store(cfg))


def _base_preset(args: argparse.Namespace) -> str:
    """The preset a new run starts from: ``--preset``, else the ``--config`` file's ``preset`` (one of
    :data:`PRESETS`; "custom" or none: :data:`DEFAULT_PRESET`), else :data:`DEFAULT_PRESET`. Both named and
    different is an error."""
    named = None
    if args.config is not None:
        named = read_json_object(Path(args.config), "--config file").get("preset")
        named = named if named in PRESETS else None
    if args.preset is not None and named is not None and args.preset != named:
        raise DepthnerfError(f"{args.config}: a {named} config, but --preset {args.preset}; drop one of them")
    return args.preset or named or DEFAULT_PRESET


def resolve_config(args: argparse.Namespace) -> TrainConfig:
    """Preset -> --config file -> --depth -> named flags -> --section.field overrides; on --resume the run's own
    config takes the preset's place."""
    if args.resume and args.out and (Path(args.out) / "config.json").is_file():
        return _resume_config(args, Path(args.out) / "config.json")
    checkpoints = Path(args.out) / "checkpoints" if args.resume and args.out else None
    if checkpoints is not None and checkpoints.is_dir() and any(checkpoints.iterdir()):
        raise DepthnerfError(f"{Path(args.out) / 'config.json'}: missing, so the run's checkpoints cannot be resumed "
                             "with the settings they were trained with; restore it, or train a new run in another "
                             "--out")
    cfg = _apply_flags(_with_config_file(preset(_base_preset(args)), args), args)
    root = Path(cfg.data.root)
    return check_config(_absolute_store(dataclasses.replace(cfg, data=dataclasses.replace(cfg.data,
                                                                                        root=str(root.resolve())))))


def _absolute_store(cfg: TrainConfig) -> TrainConfig:
    """``data.view_store`` as an absolute path (so that ``--resume`` from another folder finds the same store)."""
    store = cfg.data.view_store
    return dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, view_store=str(Path(store).resolve()))
                               ) if store else cfg


def run(args: argparse.Namespace) -> int:
    try:  # from the command line (and the run's config) alone: every torchrun rank refuses alike, rank 0 prints it
        cfg = resolve_config(args)
        if args.print_config:
            print(json.dumps(to_dict(cfg), indent=2))
            return 0
        if not args.out:
            raise DepthnerfError("--out RUN_DIR is required to train")
        if in_dataset(Path(args.out), Path(cfg.data.root)):  # its folders would be read as objects or splits
            raise DepthnerfError(f"{args.out}: --out is the dataset {cfg.data.root} or lies in one of its split "
                                 "folders, which training reads; choose an --out outside them")
        from depthnerf.distributed import checked_together, setup, teardown
        from depthnerf.eval.validation import validate
        from depthnerf.train.loop import train
    except DepthnerfError as err:
        raise refusal(str(err), launch_rank()) from None
    info = setup(args.device, deterministic=args.deterministic)  # a device refusal: printed once (setup says how)
    try:
        if args.strict:  # training checks every file itself (leniently); this makes optional parts strict too
            with checked_together(info, "checking the data (--strict)"):  # the ranks may read their own copies
                _check_strictly(cfg)
        result = train(cfg, Path(args.out), info, resume=args.resume, progress=not args.no_progress,
                       validate=validate, compile=args.compile, compile_step=args.compile_step)
    finally:
        teardown(info)
    if info.is_main:
        print(json.dumps(result, allow_nan=False))
        if result["stopped_by"]:
            print(f"stopped by {result['stopped_by']} at step {result['step']}: checkpoint {result['checkpoint']}; "
                  f"resume with: {resume_command(args, info.world)}", file=sys.stderr, flush=True)
    return int(result["exit_code"])


def _check_strictly(cfg: TrainConfig) -> None:
    """``--strict``: index the train and val splits strictly (a problem in an optional part is an error)."""
    from depthnerf.data.srn import index_split, split_dir

    for split in ("train", "val"):
        if split == "train" or split_dir(cfg.data.root, cfg.data.category, split).is_dir():
            index_split(cfg.data.root, cfg.data.category, split, strict=True)


def resume_command(args: argparse.Namespace, world: int) -> str:
    """The one command that continues this run: ``depthnerf train --out RUN --resume`` plus the flags that are
    not stored in the run's config (device, determinism, compilation, strictness); under torchrun the same launch."""
    cmd = ["depthnerf", "train", "--out", str(Path(args.out).resolve()), "--resume"]
    cmd += ["--device", args.device] if args.device != "auto" else []
    cmd += [flag for flag, on in (("--deterministic", args.deterministic), ("--compile", args.compile),
                                  ("--compile-step", args.compile_step),
                                  ("--strict", args.strict), ("--no-progress", args.no_progress)) if on]
    text = shlex.join(cmd)
    if world > 1:
        per_node = int(os.environ.get("LOCAL_WORLD_SIZE", world))
        nodes = max(1, world // max(1, per_node))
        launch = (f"torchrun --nproc_per_node={per_node}" if nodes == 1 else
                  f"torchrun --nnodes={nodes} --nproc_per_node={per_node} <your rendezvous flags, on every node>")
        text = f"{launch} -m {text}"
    return text
