"""What a facing head's plane is worth when the head is unsure: the head's plane against no plane, by confidence.

For each of ``--objects`` test objects, ``--views-per-object`` input views are drawn at random (seeded, as
``depthnerf fit-facing`` and ``scripts/facing_head_error.py`` draw them: :func:`depthnerf.train.facing_head
.drawn_views`), so the cases cover the spiral's elevations and facings, not only the side views of
``scripts/facing_study.py``. Each case is encoded from its input view alone, the head's plane and confidence are
read (:func:`depthnerf.infer.facing.head_facing`), and the protocol's target views
(every ``--views-stride``-th of the others) are rendered and scored (PSNR) with three planes: ``true`` (the
dataset's), ``head`` and ``none``. ``gated`` is what ``reconstruct --facing auto --facing-min-confidence T``
does (:func:`depthnerf.infer.facing.fit_facing`): the head's plane, or no plane where the confidence is below
``T`` (no further renders). ``--inputs dataset`` encodes the view as the evaluation does; ``--inputs photo``
as ``reconstruct`` encodes a photo of it: recentred and scaled to the model's fill
(:func:`depthnerf.train.facing_head.encodings`, as ``fit-facing --inputs photo``), the prior computed from the
framed image, and the camera's intrinsics those of the framed image, so the targets keep their true cameras.
Photos are where the head is unsure more often (``scripts/facing_head_error.py --photo``).

Prints, per confidence bin, the head's angle error and the head's plane against no plane; the same for the cases
read more than 15 and 30 degrees off; then, per threshold (``--thresholds``), how many cases the gate sends to no
plane and the gated PSNR against the head's and the true plane's. Intervals are 95% t-intervals over objects (each object's cases averaged first: the views of one object
are not independent)::

    python scripts/facing_gate_study.py --checkpoint cpu-chairs-sym-pp --data unseen --category chairs \\
        --objects 20 --views-per-object 8 [--inputs photo] --json gate-chairs.json

With ``--json`` every case is written as soon as it is scored (``{"settings": ..., "cases": [...]}``, replaced
atomically), and a run that finds the file holding cases of the same settings renders only the missing ones: an
interrupted run resumes where it stopped. A file of other settings is refused, naming the setting.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import torch
from paired_difference import t_interval

from depthnerf.data.photo_framing import category_fill
from depthnerf.data.protocol import protocol_views
from depthnerf.data.symmetry import facing_plane, relative_facing
from depthnerf.errors import DepthnerfError
from depthnerf.eval.metrics import psnr
from depthnerf.files import write_json_atomic
from depthnerf.infer.facing import head_facing, with_plane
from depthnerf.model.facing_head import angle_error
from depthnerf.train.facing_head import FacingHeadConfig, dataset_session, drawn_views, encodings

PLANES = ("true", "head", "none")
"""The planes rendered per case."""
BINS = (0.0, 0.3, 0.4, 0.5, 0.6, 0.8, float("inf"))
"""Edges of the confidence bins of the printed table."""
FAR_OFF = (15.0, 30.0)
"""Angle errors (degrees) beyond which the report also gives the head's plane against no plane."""


def object_interval(cases: list[dict], value) -> str:
    """Mean of ``value(case)`` over the cases, with the 95% t-interval over per-object means."""
    per_object: dict[str, list[float]] = {}
    for c in cases:
        per_object.setdefault(c["object"], []).append(value(c))
    mean = float(np.mean([value(c) for c in cases]))
    _, _, half = t_interval([float(np.mean(v)) for v in per_object.values()])
    return f"{mean:+.2f} [{mean - half:+.2f}, {mean + half:+.2f}]"


SETTINGS = ("checkpoint", "data", "category", "split", "objects", "views_per_object", "seed", "views_stride", "inputs")
"""The arguments that decide the cases; a ``--json`` file to resume must hold the same."""


def load_cases(path: Path) -> tuple[dict | None, list[dict]]:
    """The settings and cases of a ``--json`` file; a list (files written before the settings were) has none."""
    data = json.loads(path.read_text())
    if isinstance(data, list):
        return None, data
    if not isinstance(data, dict) or not isinstance(data.get("cases"), list):
        raise DepthnerfError(f"{path}: not a facing_gate_study file (a list of cases or settings and cases expected)")
    return data.get("settings"), data["cases"]


def resumed_cases(path: Path | None, settings: dict) -> dict[tuple[str, int], dict]:
    """The cases already in ``path`` by (object, view), after checking that it was written with ``settings``."""
    if path is None or not path.exists():
        return {}
    found, cases = load_cases(path)
    if found is None:
        raise DepthnerfError(f"{path}: holds cases without their settings; pass another --json to render afresh")
    for key in SETTINGS:
        if found.get(key) != settings[key]:
            raise DepthnerfError(f"{path}: holds cases of {key} {found.get(key)!r}, this run has {settings[key]!r}; "
                                 "pass another --json or the same settings")
    print(f"resuming: {len(cases)} cases from {path}", file=sys.stderr)
    return {(c["object"], c["view"]): c for c in cases}


def run_cases(args: argparse.Namespace) -> list[dict]:
    """Render and score every case (module docstring), skipping those an earlier run wrote to ``--json``."""
    settings = {key: str(v) if isinstance(v := getattr(args, key), Path) else v for key in SETTINGS}
    done = resumed_cases(args.json, settings)
    draw = FacingHeadConfig(data=args.data, category=args.category, split=args.split, objects=args.objects,
                            views_per_object=args.views_per_object, seed=args.seed, inputs=args.inputs)
    session, records = dataset_session(args.checkpoint, draw)
    if session.pretrained.facing_head is None:
        raise DepthnerfError(f"{args.checkpoint}: carries no facing head (depthnerf fit-facing writes one)")
    true_plane, _ = session.dataset_symmetry(args.category)
    if true_plane is None or not any(true_plane[:3]):
        raise DepthnerfError(f"{args.data}: no mirror plane for {args.category}")
    fill = category_fill(session.spec.category, session.framing)
    cases = []
    for record, picks in zip(records, drawn_views(records, draw), strict=True):
        for view in picks:
            if (record.object_id, view) in done:
                cases.append(done[(record.object_id, view)])
                continue
            src = session.load_views(record, [view], session.spec.resolution,
                                     with_depth=session.prior_source.needs_depths)
            encoded = next(encodings(session, src, args.inputs, true_plane, fill))
            targets = protocol_views(record.num_views, args.views_stride, inputs=[view]).targets
            tgt = session.load_views(record, list(targets), session.spec.resolution)
            reading = head_facing(session, encoded)
            pose = encoded.pose.double().cpu().numpy()
            planes = {"true": tuple(true_plane), "head": facing_plane(reading.facing), "none": None}
            gts = tgt.images.permute(0, 2, 3, 1).numpy()
            scores = {}
            for name in PLANES:
                enc = dataclasses.replace(encoded, enc=with_plane(encoded.enc, planes[name]))
                rgb = session.render(enc, tgt.poses, tgt.intrinsics).rgb.numpy()
                scores[name] = float(np.mean([psnr(rgb[k], gts[k]) for k in range(len(gts))]))
            psi_true = relative_facing(true_plane, pose)
            psi_head = relative_facing(planes["head"], pose)
            case = {"object": record.object_id, "view": view, "confidence": reading.confidence,
                    "head_angle_error": float(angle_error(psi_head, psi_true)), "psnr": scores}
            cases.append(case)
            if args.json:
                write_json_atomic(args.json, {"settings": settings, "cases": cases})
            print(f"{record.object_id} view {view}: confidence {reading.confidence:.2f}, head "
                  f"{case['head_angle_error']:+.1f} deg; PSNR " + " ".join(f"{k} {v:.2f}" for k, v in scores.items()),
                  file=sys.stderr, flush=True)
    return cases


def gated(case: dict, threshold: float) -> float:
    """The PSNR of the gated choice: no plane below ``threshold``, else the head's."""
    return case["psnr"]["none" if case["confidence"] < threshold else "head"]


def report(cases: list[dict], thresholds: list[float]) -> None:
    """The printed tables (module docstring)."""
    mean = {k: np.mean([c["psnr"][k] for c in cases]) for k in PLANES}
    print(f"{len(cases)} cases, {len({c['object'] for c in cases})} objects; PSNR "
          + ", ".join(f"{k} {v:.2f}" for k, v in mean.items()))
    print("confidence bin | cases | head |angle error| median, 90th pct | head - none (dB) | head - true (dB)")
    for lo, hi in zip(BINS[:-1], BINS[1:], strict=True):
        sel = [c for c in cases if lo <= c["confidence"] < hi]
        if not sel:
            continue
        err = np.abs([c["head_angle_error"] for c in sel])
        print(f"[{lo:.1f}, {hi:.1f}) | {len(sel)} | {np.median(err):.1f}, {np.quantile(err, 0.9):.1f} | "
              f"{object_interval(sel, lambda c: c['psnr']['head'] - c['psnr']['none'])} | "
              f"{object_interval(sel, lambda c: c['psnr']['head'] - c['psnr']['true'])}")
    for off in FAR_OFF:
        sel = [c for c in cases if abs(c["head_angle_error"]) > off]
        if sel:
            print(f"head's plane more than {off:g} degrees off: {len(sel)} cases, head - none "
                  f"{object_interval(sel, lambda c: c['psnr']['head'] - c['psnr']['none'])} dB")
    print("threshold | to no plane | gated - head (dB) | gated - true (dB)")
    for t in thresholds:
        print(f"{t:g} | {sum(c['confidence'] < t for c in cases)}/{len(cases)} | "
              f"{object_interval(cases, lambda c, t=t: gated(c, t) - c['psnr']['head'])} | "
              f"{object_interval(cases, lambda c, t=t: gated(c, t) - c['psnr']['true'])}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--checkpoint", required=True, help="a mirror checkpoint with a facing head")
    ap.add_argument("--data", required=True, type=Path, help="dataset root")
    ap.add_argument("--category", required=True, help="category folder prefix, e.g. chairs")
    ap.add_argument("--split", default="test", choices=("train", "val", "test"), help="split (default test)")
    ap.add_argument("--objects", type=int, default=20, help="at most N objects (default 20)")
    ap.add_argument("--views-per-object", type=int, default=8, help="input views drawn per object (default 8)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the view draw")
    ap.add_argument("--views-stride", type=int, default=50, help="score every K-th other view (default 50)")
    ap.add_argument("--inputs", choices=("dataset", "photo"), default="dataset",
                    help="encode each input view as the evaluation does (default) or framed as reconstruct frames a "
                         "photo")
    ap.add_argument("--thresholds", type=float, nargs="+", default=[0.3, 0.4, 0.5, 0.6],
                    help="confidence thresholds of the gate to report (default 0.3 0.4 0.5 0.6)")
    ap.add_argument("--from-json", type=Path, nargs="+",
                    help="report the cases of earlier --json files (e.g. runs with other seeds) instead of rendering")
    ap.add_argument("--json", type=Path, help="write every case here as it is scored; a run finding the file resumes "
                                                 "it (module docstring)")
    args = ap.parse_args(argv)
    try:
        with torch.no_grad():
            cases = ([c for f in args.from_json for c in load_cases(f)[1]] if args.from_json
                     else run_cases(args))
    except (DepthnerfError, OSError, json.JSONDecodeError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    if not cases:
        print("error: no cases", file=sys.stderr)
        return 2
    report(cases, args.thresholds)
    return 0


if __name__ == "__main__":
    sys.exit(main())
