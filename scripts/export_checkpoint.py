"""Export a training run's checkpoint as a shipped fp16 checkpoint with its model card.

``python scripts/export_checkpoint.py --run RUN_DIR --name cpu-cars-depth
[--eval-summary RUN_DIR/eval/test/summary.json] [--out depthnerf/checkpoints] [--command "the training command"]``

Writes into ``--out`` (default: the package's ``depthnerf/checkpoints``, where ``depthnerf checkpoints`` and
``--checkpoint <name>`` find it):

``<name>.safetensors``
    The run's ``checkpoints/best`` (else its latest checkpoint; :func:`depthnerf.pretrained.load.resolve_checkpoint`)
    with floating tensors in float16 and integer buffers (BatchNorm ``num_batches_tracked``) unchanged, written
    atomically by :func:`depthnerf.train.checkpoint.save_weights`. Metadata: the source's model ``config``,
    ``train_config`` and ``step``, plus provenance ``source_sha256``, ``source_run``, ``source_file``,
    ``dtype``, ``exported_by`` and ``total_steps`` (the steps behind the weights in all, a warm start's chain
    included: :func:`steps_behind`). :func:`~depthnerf.pretrained.load.load_pretrained` casts the weights back to
    fp32.
``<name>.json``
    Name, preset, depth estimator, category, resolution, step, total steps, SHA-256 and size of the fp16 file, the
    source, the fp16 round-trip check, and with ``--eval-summary`` the metrics (``psnr``, ``ssim``, and ``lpips``,
    ``chamfer_l1``, ``fscore`` when measured) and the protocol of that ``summary.json`` (keys of
    :mod:`depthnerf.eval.table` / :mod:`depthnerf.eval.protocol`). ``depthnerf checkpoints`` prints them.
``<name>.md``
    The model card: what the model is, training data (from ``RUN/data_card.json``), preset and key settings,
    metrics with their protocol, the reproduce commands, intended use, limitations and licence
    (``scripts/checkpoint_card.py``).

``--facing-head FILE`` (a weights file written by ``depthnerf fit-facing``) copies that file's facing head into the
exported weights (:mod:`depthnerf.model.facing_head`); the head must have been fitted on this run's encoder (the
fingerprint of its float16-rounded weights), and ``--facing-command`` records how it was fitted in the cards.

A run that has not reached its ``schedule.max_steps`` (stopped early, or still training) is refused unless
``--allow-unfinished`` (then the cards say where it stopped); an ``--eval-summary`` must be of this checkpoint (its
SHA-256, before or after export), its preset and category, and its own depth prior (estimator and weights).

Round-trip check (always run, the export fails when it does not hold): the source (fp32) and the exported (fp16,
loaded back to fp32) models render the same :func:`probe_sources` input view from another camera at the training
resolution; the largest absolute RGB difference must stay below :data:`FP16_TOLERANCE`.

Portable cards: paths in the cards are relative (to the repository root by default, ``--relative-to``), and the
user's home directory in eval messages is written as ``~``, so a card says nothing about the machine that made
it. The cards also record the training data's ``framing`` and ``generator`` (from the dataset card; ``legacy``
for data of generator ``depthnerf-synth-1``), which ``depthnerf demo`` reads to synthesise matching objects.
``scripts/fix_checkpoint_cards.py`` rewrites existing card pairs that way without touching the weights.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the sibling checkpoint_card.py, however this runs
from checkpoint_card import METRIC_KEYS, eval_command, model_card  # noqa: E402

from depthnerf import __version__  # noqa: E402
from depthnerf.data.srn import category_defaults  # noqa: E402
from depthnerf.data.synth.framing import card_framing  # noqa: E402
from depthnerf.depth.normalize import normalize_disparity  # noqa: E402
from depthnerf.errors import DepthnerfError  # noqa: E402
from depthnerf.eval.metrics import psnr  # noqa: E402
from depthnerf.eval.table import load_summary  # noqa: E402
from depthnerf.files import read_json_object, sha256_file, write_text_atomic  # noqa: E402
from depthnerf.model.facing_head import FacingHead, check_encoder, head_from_tensors  # noqa: E402
from depthnerf.model.pixelnerf import SourceViews  # noqa: E402
from depthnerf.pretrained.load import SHIPPED_DIR, Pretrained, load_pretrained, resolve_checkpoint  # noqa: E402
from depthnerf.pretrained.spec import SPEC_KEY, InferenceSpec  # noqa: E402
from depthnerf.pretrained.weights import latest_checkpoint, save_with_head  # noqa: E402
from depthnerf.reconstruct.orbit import orbit_poses, srn_intrinsics  # noqa: E402
from depthnerf.render.views import render_poses  # noqa: E402
from depthnerf.train import checkpoint as ckpt  # noqa: E402
from depthnerf.train.config import TrainConfig, from_dict_config  # noqa: E402
from depthnerf.train.warm_start import steps_in_all  # noqa: E402

FP16_TOLERANCE = 0.02
"""Largest accepted absolute RGB difference (in [0, 1], ~5 of 255 levels) between fp32 and fp16 renders."""
FP16_MAX = 65504.0
"""Largest finite float16 value: a weight beyond it cannot be exported."""
NAME_PATTERN = re.compile(r"^[a-z0-9][a-z0-9._-]*$")
"""Allowed checkpoint names (they become file names and ``--checkpoint`` values)."""
REPO_ROOT = Path(__file__).resolve().parent.parent
"""Default base of the relative paths written into cards."""


def portable_path(path: str | Path | None, base: Path = REPO_ROOT) -> str | None:
    """``path`` as a POSIX path relative to ``base`` when absolute (unchanged when already relative)."""
    if path is None:
        return None
    p = Path(path)
    if not p.is_absolute():
        return p.as_posix()
    return Path(os.path.relpath(p, base.resolve())).as_posix()


def portable_text(text: str | None, base: Path = REPO_ROOT) -> str | None:
    """Free text (eval status messages) with ``base`` written as ``.`` and the home directory as ``~``."""
    if text is None:
        return None
    text = text.replace(str(base.resolve()) + "/", "")
    home = str(Path.home())
    return text.replace(home + "/", "~/") if home not in ("", "/") else text


@dataclass(frozen=True)
class ExportResult:
    """What :func:`export` wrote."""

    weights: Path
    """``<out>/<name>.safetensors``."""
    card_json: Path
    """``<out>/<name>.json``."""
    card_md: Path
    """``<out>/<name>.md``."""
    card: dict
    """The content of ``card_json``."""


def probe_sources(spec: InferenceSpec) -> tuple[SourceViews, torch.Tensor]:
    """A procedural input view (a shaded disc on white, with a dome-shaped disparity prior) at the training
    resolution and category camera, and a second camera pose 60 degrees around the object to render."""
    res = spec.resolution
    cat = category_defaults(spec.category)
    poses = orbit_poses(cat.camera_radius, 20.0, 6)
    intr = srn_intrinsics(cat.focal, cat.image_size, res)
    yy, xx = torch.meshgrid(torch.arange(res, dtype=torch.float32), torch.arange(res, dtype=torch.float32),
                            indexing="ij")
    r = torch.sqrt((xx - res / 2) ** 2 + (yy - res / 2) ** 2) / res
    mask = r < 0.3
    disc = torch.stack([0.8 - r, 0.3 + r, torch.full_like(r, 0.5)])
    image = torch.where(mask[None], disc, torch.ones_like(disc))
    normalized = None
    if spec.depth_aware:
        disparity = torch.where(mask, 1.0 - r, torch.zeros_like(r))
        normalized = normalize_disparity(disparity[None], mask[None])[None, :, None]
    src = SourceViews(images=image[None, None], poses=poses[:1][None], focal=torch.tensor([intr.focal]),
                      principal=torch.tensor([[intr.cx, intr.cy]]), disparity=normalized)
    return src, poses[1:2]


@torch.no_grad()
def roundtrip_check(source: Pretrained, exported: Pretrained) -> dict:
    """Render the probe view with both models; ``max_abs_rgb``, ``mean_abs_rgb`` and ``psnr_db`` of the pair."""
    spec = source.spec
    src, pose = probe_sources(spec)
    cat = category_defaults(spec.category)
    intr = srn_intrinsics(cat.focal, cat.image_size, spec.resolution)
    near, far = spec.z_range
    rgbs = []
    for pre in (source, exported):
        enc = pre.model.encode(src)
        rgbs.append(render_poses(pre.model, enc, pose, intr, near, far, spec.render, 4096, "cpu").rgb[0].numpy())
    diff = np.abs(rgbs[0] - rgbs[1])
    return {"max_abs_rgb": float(diff.max()), "mean_abs_rgb": float(diff.mean()),
            "psnr_db": psnr(rgbs[1], np.clip(rgbs[0], 0.0, 1.0)), "tolerance": FP16_TOLERANCE,
            "input": "procedural disc view at the training resolution, rendered from 60 degrees around"}


def read_eval_summary(path: Path, source_sha: str, exported_sha: str, cfg: TrainConfig,
                      prior_hash: str | None = None) -> dict:
    """The checked ``summary.json`` of an evaluation of this checkpoint (source or exported file) as it ships: the
    same preset and category, and its own depth prior (``depthnerf eval --depth`` / ``--depth-checkpoint`` score
    another prior: the estimator must be the checkpoint's, and the prior's weights hash, where both record one,
    ``prior_hash``)."""
    load_summary(path)  # required keys and types (depthnerf.eval.table)
    summary = read_json_object(path, "eval summary")
    if summary["checkpoint_sha256"] not in (source_sha, exported_sha):
        raise DepthnerfError(f"{path}: evaluates checkpoint {summary['checkpoint_sha256'][:12]}, not the exported "
                             f"one ({source_sha[:12]} before export, {exported_sha[:12]} after)")
    if summary["category"] != cfg.data.category or summary["preset"] != cfg.preset:
        raise DepthnerfError(f"{path}: summary is for {summary['preset']}/{summary['category']}, the checkpoint is "
                             f"{cfg.preset}/{cfg.data.category}")
    if summary["depth_prior"] != cfg.prior.estimator:
        raise DepthnerfError(f"{path}: evaluates the checkpoint with the {summary['depth_prior']} depth prior, but it "
                             f"ships with {cfg.prior.estimator}; evaluate it without --depth")
    provenance = summary.get("depth_prior_provenance")
    scored_hash = provenance.get("weights_hash") if isinstance(provenance, dict) else None
    if prior_hash and scored_hash and scored_hash != prior_hash:
        raise DepthnerfError(f"{path}: evaluates the checkpoint with other depth weights "
                             f"({provenance.get('checkpoint')}, sha256 {scored_hash[:12]}) than it was trained with "
                             f"({prior_hash[:12]}); evaluate it without --depth-checkpoint")
    return summary


def check_finished(run: Path, allow_unfinished: bool = False) -> dict | None:
    """None when the run's newest complete checkpoint reached its ``schedule.max_steps``; else (a run stopped early,
    or still training) a one-line error, or with ``allow_unfinished`` the card's record of it
    (``{"stopped_at": step, "max_steps": n}``)."""
    ckpt_root = run / "checkpoints"
    newest = latest_checkpoint(ckpt_root)
    if newest is None:
        newest = ckpt_root / "best"
    _, meta = ckpt.read_weights(newest / "model.safetensors")
    try:
        max_steps = int(json.loads(meta["train_config"])["schedule"]["max_steps"])
        step = int(meta["step"])
    except (KeyError, TypeError, ValueError):
        raise DepthnerfError(f"{newest / 'model.safetensors'}: no step and training config with "
                             "schedule.max_steps in its metadata") from None
    if step >= max_steps:
        return None
    if not allow_unfinished:
        raise DepthnerfError(f"{run}: the run is not finished (its newest checkpoint is step {step} of {max_steps}: "
                             "stopped early or still training); finish it (depthnerf train --resume), or pass "
                             "--allow-unfinished to export it as it is")
    return {"stopped_at": step, "max_steps": max_steps}


def steps_behind(warm: dict) -> int:
    """The steps behind a warm start's source in all (``init_from.json``'s ``total_steps``; for a record written
    before that field, :func:`~depthnerf.train.warm_start.steps_in_all` of the source file when it still holds the
    recorded weights, else the source's own ``step``)."""
    if isinstance(warm.get("total_steps"), int):
        return warm["total_steps"]
    step, path = int(warm.get("step") or 0), Path(str(warm.get("path", "")))
    if path.is_file() and sha256_file(path) == warm.get("sha256"):
        return steps_in_all(path, ckpt.read_weights(path)[1], warm["sha256"])
    return step


DATASET_KEYS = ("counts", "resolution", "seed", "framing", "family", "generator")
"""What the card keeps of the evaluation data's dataset card: enough to make it again (``synth_command``)."""


def _eval_section(summary: dict, path: Path, data_card: dict, base: Path = REPO_ROOT) -> dict:
    """The card's ``evaluation`` entry; ``data_card`` is the run's (its training data)."""
    keys = ("split", "objects", "views", "views_stride", "max_objects", "resolution", "input_resolution",
            "method", "metrics_path", "aggregation", "lpips_status", "fscore_tau", "mesh_status",
            "checkpoint_sha256")
    evaluated = summary.get("data_card") or {}
    section = {"summary": portable_path(path.resolve(), base), **{k: summary.get(k) for k in keys},
               "data_root": portable_path(evaluated.get("root"), base),
               "train_data_root": portable_path(data_card.get("root"), base)}
    if isinstance(evaluated.get("card"), dict):
        section["dataset"] = {k: evaluated["card"][k] for k in DATASET_KEYS if k in evaluated["card"]}
    for key in ("lpips_status", "mesh_status"):
        section[key] = portable_text(section[key], base)
    return section


def _check_fp16_range(pre: Pretrained) -> None:
    for key, value in pre.model.state_dict().items():
        if value.is_floating_point() and not bool((value.abs() <= FP16_MAX).all()):
            raise DepthnerfError(f"{pre.path}: tensor {key} has values beyond the float16 range (|x| > {FP16_MAX:g}) "
                                 "or non-finite values; cannot export as fp16")


def read_facing_head(path: Path, source: Pretrained) -> FacingHead:
    """The facing head stored in ``path``, checked to be fitted on ``source``'s encoder."""
    tensors, meta = ckpt.read_weights(path)
    head = head_from_tensors(tensors, meta, str(path))
    if head is None:
        raise DepthnerfError(f"--facing-head {path}: the file carries no facing head (write one with depthnerf "
                             "fit-facing)")
    check_encoder(head, source.model, f"--facing-head {path}")
    return head


def export(run: Path, name: str, out: Path = SHIPPED_DIR, summary_path: Path | None = None,
           command: str | None = None, data_root: str | None = None, base: Path = REPO_ROOT,
           allow_unfinished: bool = False, facing_head: Path | None = None,
           facing_command: str | None = None) -> ExportResult:
    """Export ``run``'s best (else latest) checkpoint as ``out/<name>.*`` (see the module docstring); an unfinished
    run only with ``allow_unfinished`` (:func:`check_finished`)."""
    if not NAME_PATTERN.match(name):
        raise DepthnerfError(f"--name {name!r}: use lower-case letters, digits, '.', '_' and '-' only")
    run = Path(run)
    if not (run / "checkpoints").is_dir():
        raise DepthnerfError(f"{run}: not a run folder (no checkpoints/)")
    resolve_checkpoint(run)  # no complete checkpoint: one line
    unfinished = check_finished(run, allow_unfinished)
    data_card = read_json_object(run / "data_card.json", "run data card")
    prior = read_json_object(run / "prior.json", "run prior record") if (run / "prior.json").is_file() else None
    source_path = resolve_checkpoint(run)
    _, meta = ckpt.read_weights(source_path)
    source = load_pretrained(source_path)
    _check_fp16_range(source)
    cfg = from_dict_config(json.loads(meta["train_config"]), where=f"{source_path} train_config")
    warm = (read_json_object(run / "init_from.json", "run warm-start record")
            if (run / "init_from.json").is_file() else None)
    behind = steps_behind(warm) if warm is not None else 0  # may hash the source file: once
    total_steps = source.step + behind
    out.mkdir(parents=True, exist_ok=True)
    weights, staged = out / f"{name}.safetensors", out / f".{name}.export.safetensors"
    if warm is not None and weights.is_file() and warm.get("sha256") == sha256_file(weights):
        warm = {**warm, "source": name}  # started from a copy of the checkpoint this export replaces: its successor
    extra = {"train_config": meta["train_config"], "source_sha256": source.sha256, "source_run": run.resolve().name,
             "source_file": source_path.resolve().relative_to(run.resolve()).as_posix(), "dtype": "float16",
             "exported_by": f"scripts/export_checkpoint.py (depthnerf {__version__})",
             "total_steps": str(total_steps), SPEC_KEY: source.spec.to_json()}
    head = read_facing_head(Path(facing_head), source) if facing_head is not None else None
    ckpt.save_weights(staged, source.model, ckpt.checkpoint_config(meta, source_path), step=source.step,
                      dtype=torch.float16, extra=extra)
    try:  # every check passes and both cards are built before any file takes its shipped name
        if head is not None:
            save_with_head(staged, head, staged)
        exported = load_pretrained(staged)
        check = roundtrip_check(source, exported)
        if not check["max_abs_rgb"] <= FP16_TOLERANCE:
            raise DepthnerfError(f"{weights}: fp16 weights render up to {check['max_abs_rgb']:.3g} away from the "
                                 f"fp32 ones (tolerance {FP16_TOLERANCE}); not exported")
        summary = None
        if summary_path is not None:
            trained_prior = source.spec.prior_weights_hash or (prior or {}).get("weights_hash")  # spec, else run
            summary = read_eval_summary(Path(summary_path), source.sha256, exported.sha256, cfg, trained_prior)
        card = {"name": name, "preset": cfg.preset, "depth_estimator": cfg.prior.estimator,
                "depth_weights": exported.spec.prior.checkpoint,
                "category": cfg.data.category, "resolution": cfg.data.resolution, "step": exported.step,
                "total_steps": total_steps, "sha256": exported.sha256, "size_bytes": staged.stat().st_size,
                "dtype": "float16",
                "source": {"run": extra["source_run"], "file": extra["source_file"], "sha256": source.sha256},
                "fp16_check": check, "command": command, "data_root": portable_path(data_root, base),
                "run_path": portable_path(run, base), "metrics": None, "protocol": None, "evaluation": None}
        if unfinished is not None:
            card["unfinished"] = unfinished
        if head is not None:
            card["facing_head"] = {**head.describe(), "command": portable_text(facing_command, base)}
        ds = data_card.get("dataset_card") or {}
        if ds:
            card.update(framing=card_framing(ds), generator=ds.get("generator"))
        card["pixel_center"] = cfg.data.pixel_center
        if warm is not None:
            # a shipped checkpoint's name (kept as is) or a path (written relative, like the card's other paths)
            card["init_from"] = {"source": portable_path(warm.get("source"), base), "step": warm.get("step"),
                                 "total_steps": behind, "sha256": warm.get("sha256")}
        if summary is not None:
            card["metrics"] = {k: float(summary[k]) for k in METRIC_KEYS if summary.get(k) is not None}
            card["protocol"] = summary["protocol"]
            card["evaluation"] = _eval_section(summary, Path(summary_path), data_card, base)
            card["eval_command"] = eval_command(name, card, cfg.data.resolution)
        card_text = model_card(card, cfg, data_card, prior)
    except BaseException:
        staged.unlink(missing_ok=True)
        raise
    os.chmod(staged, 0o644)  # shared package data (the writer's temporary file may be private)
    os.replace(staged, weights)  # then the cards (a rename and two atomic writes: no step left that can refuse)
    card_json, card_md = out / f"{name}.json", out / f"{name}.md"
    write_text_atomic(card_json, json.dumps(card, indent=1) + "\n")
    write_text_atomic(card_md, card_text)
    return ExportResult(weights=weights, card_json=card_json, card_md=card_md, card=card)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", type=Path, required=True, help="training run folder")
    p.add_argument("--name", required=True, help="shipped name, e.g. cpu-cars-depth")
    p.add_argument("--eval-summary", type=Path, help="summary.json of 'depthnerf eval' of this run's checkpoint")
    p.add_argument("--out", type=Path, default=SHIPPED_DIR, help=f"output folder (default {SHIPPED_DIR})")
    p.add_argument("--command", help="the command that produced the run (quoted; goes into the model card)")
    p.add_argument("--data-root", help="dataset root as the card's reproduce commands should name it (default: the "
                   "path the evaluation used, relative to --relative-to)")
    p.add_argument("--allow-unfinished", action="store_true",
                   help="export a run that stopped before its --max-steps (the card says so); refused otherwise")
    p.add_argument("--facing-head", type=Path, help="a weights file from 'depthnerf fit-facing' whose facing head "
                   "(fitted on this run's encoder) the export carries")
    add_card_arguments(p)
    return p.parse_args(argv)


def add_card_arguments(p: argparse.ArgumentParser) -> None:
    """``--facing-command`` and ``--relative-to``, as this script and ``scripts/attach_facing_head.py`` take them."""
    p.add_argument("--facing-command", help="the fit-facing command (quoted; goes into the model card)")
    p.add_argument("--relative-to", type=Path, default=REPO_ROOT,
                   help=f"base of the relative paths written into cards (default the repository, {REPO_ROOT})")


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        with torch.no_grad():  # scoped: main() also runs inside test processes
            res = export(args.run, args.name, args.out, args.eval_summary, args.command, args.data_root,
                         args.relative_to, args.allow_unfinished, args.facing_head, args.facing_command)
    except DepthnerfError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    c = res.card
    metrics = ", ".join(f"{k} {v:.4f}" for k, v in (c["metrics"] or {}).items()) or "no metrics (no --eval-summary)"
    print(f"exported {c['name']}: {c['preset']} / {c['depth_estimator']}, step {c['step']}, {c['size_bytes']:,} "
          f"bytes fp16 (sha256 {c['sha256'][:12]}); fp16 vs fp32 max abs RGB {c['fp16_check']['max_abs_rgb']:.2e}; "
          f"{metrics}")
    print(f"wrote {res.weights}, {res.card_json}, {res.card_md}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
