"""How well ``--facing auto`` finds a mirror model's plane, and what the plane is worth, on a synthetic test set.

For each object and each input view (``--input-views``), the object is encoded from that view alone and its mirror
plane estimated as ``depthnerf reconstruct --facing auto`` does (:func:`depthnerf.infer.facing.fit_facing`). The
protocol's target views (every ``--views-stride``-th of the others) are then rendered and scored (PSNR, as ``eval``
scores) with these planes:

- ``true``: the dataset's plane (its card);
- ``auto``: the search over the input view's error alone (``--facing auto`` of a checkpoint without a facing
  head): ``best`` where it was kept, ``none`` where it chose no plane (the same renders, not rendered again);
- ``best``: the plane that rendered the input view best, kept or not;
- ``none``: no plane;
- ``side``: the plane reconstruct's default ``--facing 90`` assumes: the vertical plane facing the input camera,
  right for a side view only;
- ``prefer``: a side-view preference on top of ``auto`` (measured here, not in reconstruct): the side plane
  wherever its input-view error is within ``1 + --side-tolerance`` times the error of ``auto``'s choice, else
  ``auto`` (the same renders);
- with a checkpoint that carries a facing head (``depthnerf fit-facing``), also ``head``: the head's plane, which
  ``--facing auto`` takes with such a checkpoint (:func:`depthnerf.infer.facing.fit_facing`), and ``head_search``:
  the search's fine passes started at the head's plane, kept only when it renders the input view better than no
  plane (measured here, not in reconstruct).

Prints the estimate's angle error (against the true plane, modulo 180 degrees) and each plane's PSNR, per input
view and overall, with paired 95% intervals of ``auto`` against the others; ``--json`` keeps every case.
The candidate planes are vertical planes through the origin of a +z-up world, which the synthetic benchmark's
objects are (``depthnerf synth``: up +z, centred at the origin)::

    python scripts/facing_study.py --checkpoint cpu-cars-sym-pp --data cars50 --category cars --objects 12 \
        --input-views 64 74 84 94 54 --json facing-cars.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path

import numpy as np
import torch
from paired_difference import t_interval

from depthnerf.data.srn import index_split
from depthnerf.data.symmetry import facing_plane
from depthnerf.eval.metrics import psnr
from depthnerf.eval.objects import prepare_object, protocol_views
from depthnerf.infer.facing import head_facing, input_view_error, search_facing, with_plane
from depthnerf.infer.session import InferenceSession, SessionOptions
from depthnerf.model.facing_head import angle_error

PLANES = ("true", "auto", "best", "none", "side", "prefer")
RENDERED = ("true", "best", "none", "side")
"""The planes rendered; ``auto`` is ``best`` or ``none``, ``prefer`` ``side`` or ``auto``."""
HEAD_PLANES = ("head", "head_search")
"""The planes a checkpoint with a facing head adds (rendered)."""


def plane_angle(plane) -> float:
    """The facing ``a`` in [0, 180) whose :func:`~depthnerf.data.symmetry.facing_plane` is ``plane``'s (vertical)."""
    return math.degrees(math.atan2(-plane[0], plane[1])) % 180


def side_plane(c2w: torch.Tensor) -> tuple[float, float, float, float]:
    """The vertical plane through the origin whose normal is the input camera's horizontal viewing direction."""
    forward = c2w[:3, 2].double().numpy().copy()
    forward[2] = 0.0
    n = forward / np.linalg.norm(forward)
    return float(n[0]), float(n[1]), 0.0, 0.0


def interval(d: np.ndarray) -> str:
    """Mean paired difference with its 95% t-interval (``paired_difference.t_interval``)."""
    mean, _, half = t_interval(d.tolist())
    return f"{mean:+.2f} [{mean - half:+.2f}, {mean + half:+.2f}]"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--data", required=True, type=Path)
    ap.add_argument("--category", required=True)
    ap.add_argument("--split", default="test")
    ap.add_argument("--objects", type=int, default=12)
    ap.add_argument("--input-views", type=int, nargs="+", default=[64])
    ap.add_argument("--views-stride", type=int, default=50)
    ap.add_argument("--side-tolerance", type=float, default=0.5,
                    help="prefer the side plane within 1 + this of auto's input-view error (the 'prefer' column)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    if args.side_tolerance < 0:
        print(f"error: --side-tolerance must be >= 0, got {args.side_tolerance}", file=sys.stderr)
        return 2
    records = index_split(args.data, args.category, args.split).objects[: args.objects]
    session = InferenceSession(args.checkpoint, SessionOptions(inputs="dataset", data_root=args.data,
                                                               records=records))
    if not session.model.cfg.mirror:
        print(f"error: {args.checkpoint} is not a mirror model: it reads no plane", file=sys.stderr)
        return 2
    true_plane, _ = session.dataset_symmetry(args.category)
    has_head = session.pretrained.facing_head is not None
    cases = []
    for record in records:
        for view in args.input_views:
            views = protocol_views(record.num_views, args.views_stride, inputs=[view])
            obj = prepare_object(session, record, views, symmetry_plane=true_plane)
            error = input_view_error(session, obj.encoded)
            fit = search_facing(error)
            planes = {"true": tuple(true_plane), "best": facing_plane(fit.best), "none": None,
                      "side": side_plane(obj.encoded.pose)}
            side_error = error(plane_angle(planes["side"]))
            auto_error = fit.none_error if fit.facing is None else fit.error
            prefer_side = side_error <= (1 + args.side_tolerance) * auto_error
            if has_head:
                head_fit = search_facing(error, start=head_facing(session, obj.encoded).facing)
                planes["head"] = facing_plane(head_fit.start)
                planes["head_search"] = None if head_fit.facing is None else facing_plane(head_fit.facing)
            gts = obj.targets.images.permute(0, 2, 3, 1).numpy()
            scores = {}
            for name in RENDERED + (HEAD_PLANES if has_head else ()):
                enc = dataclasses.replace(obj.encoded, enc=with_plane(obj.encoded.enc, planes[name]))
                rgb = session.render(enc, obj.targets.poses, obj.targets.intrinsics).rgb.numpy()
                scores[name] = float(np.mean([psnr(rgb[k], gts[k]) for k in range(len(gts))]))
            scores["auto"] = scores["none" if fit.facing is None else "best"]
            scores["prefer"] = scores["side"] if prefer_side else scores["auto"]
            scores = {k: scores[k] for k in PLANES + (HEAD_PLANES if has_head else ())}
            true_angle = plane_angle(true_plane)
            error = angle_error(fit.best, true_angle)
            case = {"object": record.object_id, "view": view, "best": fit.best, "chosen": fit.facing,
                    "angle_error": error, "fit": fit.as_dict(), "side_error": side_error,
                    "prefer_side": prefer_side, "psnr": scores}
            if has_head:
                case["head_fit"] = head_fit.as_dict()
                case["head_angle_error"] = angle_error(head_fit.start, true_angle)
                case["head_search_angle_error"] = angle_error(head_fit.best, true_angle)
            cases.append(case)
            print(f"{record.object_id} view {view}: estimate {fit.best:g} (error {error:+.0f} deg), "
                  f"{'kept' if fit.facing is not None else 'none chosen'}; PSNR "
                  + " ".join(f"{k} {v:.2f}" for k, v in scores.items()), file=sys.stderr, flush=True)
    if args.json:
        args.json.write_text(json.dumps(cases, indent=1))
    for view in [*args.input_views, None]:
        sel = [c for c in cases if view is None or c["view"] == view]
        err = np.abs([c["angle_error"] for c in sel])
        kept = [c for c in sel if c["chosen"] is not None]
        head = "all input views" if view is None else f"input view {view}"
        print(f"{head} ({len(sel)} cases): |angle error| median {np.median(err):.1f}, within 3 deg "
              f"{np.mean(err <= 3):.0%}; plane kept {len(kept)}/{len(sel)}"
              + (f" (|error| median {np.median(np.abs([c['angle_error'] for c in kept])):.1f})" if kept else ""))
        mean = {k: np.mean([c["psnr"][k] for c in sel]) for k in sel[0]["psnr"]}
        print("  PSNR " + ", ".join(f"{k} {v:.2f}" for k, v in mean.items()))
        auto = np.array([c["psnr"]["auto"] for c in sel])
        print("  auto against " + ", ".join(
            f"{k} {interval(auto - np.array([c['psnr'][k] for c in sel]))}" for k in ("true", "best", "none", "side")))
        prefer = np.array([c["psnr"]["prefer"] for c in sel])
        print(f"  prefer (side plane in {sum(c['prefer_side'] for c in sel)}/{len(sel)}, tolerance "
              f"{args.side_tolerance:g}) against auto {interval(prefer - auto)}, better in "
              f"{int(np.sum(prefer > auto))}, worse in {int(np.sum(prefer < auto))}")
        if "head" in sel[0]["psnr"]:
            for key in HEAD_PLANES:
                e = np.abs([c[f"{key}_angle_error"] for c in sel])
                d = np.array([c["psnr"][key] for c in sel]) - auto
                print(f"  {key}: |angle error| median {np.median(e):.1f}, within 3 deg {np.mean(e <= 3):.0%}; "
                      f"against auto {interval(d)}, better in {int(np.sum(d > 0))}, worse in {int(np.sum(d < 0))}; "
                      f"against true {interval(np.array([c['psnr'][key] - c['psnr']['true'] for c in sel]))}")
            kept = sum(c["head_fit"]["facing"] is not None for c in sel)
            print(f"  head_search kept its plane in {kept}/{len(sel)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
