"""``depthnerf train``: train a preset (baseline with ``--depth none``, depth-aware otherwise).

Any config field can be overridden with ``--section.field VALUE`` (e.g. ``--model.coarse.d_hidden 256``,
``--schedule.lr 2e-4``); ``--print-config`` prints the resolved config as JSON and exits. Multi-GPU / multi-node:
launch the same command with ``torchrun --nproc_per_node=N -m depthnerf train ...``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

from depthnerf.config_io import apply_overrides, to_dict
from depthnerf.depth.estimators import ESTIMATORS
from depthnerf.errors import DepthnerfError
from depthnerf.train.config import PRESETS, TrainConfig, check_config, from_dict_config, preset, with_prior

ACCEPTS_OVERRIDES = True


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--preset", default="cpu-cars", choices=sorted(PRESETS), help="named preset (default cpu-cars)")
    p.add_argument("--data", help="dataset root (SRN layout); default: the preset's")
    p.add_argument("--out", help="run folder (config, metrics.jsonl, TensorBoard events, checkpoints/)")
    p.add_argument("--depth", choices=ESTIMATORS,
                   help="depth prior: none = pixelNeRF baseline; default: the preset's")
    p.add_argument("--depth-checkpoint", help="depth estimator weights (hub id or local dir for depth-anything-v2)")
    p.add_argument("--max-steps", type=int, help="total optimisation steps")
    p.add_argument("--checkpoint-every", type=int, help="steps between checkpoints")
    p.add_argument("--seed", type=int, help="run seed")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint")
    p.add_argument("--device", default="auto", help="auto (CUDA if available), cpu or cuda")
    p.add_argument("--print-config", action="store_true", help="print the resolved config as JSON and exit")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--strict", action="store_true",
                   help="a problem in an optional part of the data (depth/, mask/, mesh.ply) is an error")


def resolve_config(args: argparse.Namespace) -> TrainConfig:
    """Preset -> --depth -> named flags -> --section.field overrides; or the run's own config on --resume."""
    if args.resume and args.out and (Path(args.out) / "config.json").is_file():
        path = Path(args.out) / "config.json"
        try:
            cfg = from_dict_config(json.loads(path.read_text()), where=str(path))
        except (OSError, json.JSONDecodeError) as err:
            raise DepthnerfError(f"{path}: unreadable run config ({err})") from None
        if args.max_steps is not None:
            cfg = dataclasses.replace(cfg, schedule=dataclasses.replace(cfg.schedule, max_steps=args.max_steps))
        return check_config(cfg)
    cfg = preset(args.preset)
    if args.depth is not None or args.depth_checkpoint is not None:
        cfg = with_prior(cfg, args.depth or cfg.prior.estimator, args.depth_checkpoint)
    if args.data is not None:
        cfg = dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, root=args.data))
    if args.seed is not None:
        cfg = dataclasses.replace(cfg, seed=args.seed)
    sched, log = cfg.schedule, cfg.log
    if args.max_steps is not None:
        sched = dataclasses.replace(sched, max_steps=args.max_steps)
    if args.checkpoint_every is not None:
        log = dataclasses.replace(log, checkpoint_every=args.checkpoint_every)
    cfg = dataclasses.replace(cfg, schedule=sched, log=log)
    return check_config(apply_overrides(cfg, args.overrides))


def run(args: argparse.Namespace) -> int:
    cfg = resolve_config(args)
    if args.print_config:
        print(json.dumps(to_dict(cfg), indent=2))
        return 0
    if not args.out:
        raise DepthnerfError("--out RUN_DIR is required to train")
    from depthnerf.eval.validation import validate
    from depthnerf.train.distributed import setup, teardown
    from depthnerf.train.loop import train

    if args.strict:  # training checks every file itself (leniently); this makes optional parts strict too
        from depthnerf.data.srn import index_split, split_dir

        for split in ("train", "val"):
            if split == "train" or split_dir(cfg.data.root, cfg.data.category, split).is_dir():
                index_split(cfg.data.root, cfg.data.category, split, strict=True)

    info = setup(args.device)
    try:
        result = train(cfg, Path(args.out), info, resume=args.resume, progress=not args.no_progress,
                       validate=validate)
    finally:
        teardown(info)
    if info.is_main:
        print(json.dumps(result))
    return 0
