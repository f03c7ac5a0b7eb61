"""How far a checkpoint's facing head is from the true mirror plane on a dataset's views, with no rendering.

``python scripts/facing_head_error.py --checkpoint CKPT [CKPT ...] --data DIR --category C [--split test]
[--objects 20] [--views-per-object 25] [--seed 0] [--inputs dataset|photo] [--photo] [--json PATH]``

Each view is encoded as ``depthnerf fit-facing`` encodes its training views (:func:`depthnerf.train.facing_head.gather`:
the same seeded draw of views per object, one view at a time) and the head's angle is compared with the dataset's
plane (modulo 180 degrees). Prints, per checkpoint, the median, 90th percentile and share within 3 and 10 degrees of
the absolute error: a quick check of heads fitted in different ways on objects none of them saw, before the
rendering study (``scripts/facing_study.py``) measures what the plane is worth in PSNR. ``--inputs photo`` frames
each view as ``reconstruct`` frames a photo first (``fit-facing --inputs photo``'s encoding). ``--photo`` gives each
view to ``reconstruct --facing auto`` as an RGBA photo instead (:func:`photo_errors`): what a user's photo of such an
object goes through (recentring, scaling to the model's fill, the prior computed from the prepared photo).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import torch

from depthnerf import ReconstructConfig, Reconstructor
from depthnerf.data.srn import index_split
from depthnerf.data.symmetry import dataset_plane, relative_facing
from depthnerf.errors import DepthnerfError
from depthnerf.model.facing_head import angle_error
from depthnerf.train.facing_head import FacingHeadConfig, dataset_session, drawn_views, gather

UNSURE = 0.4
"""A head confidence (:meth:`depthnerf.model.facing_head.FacingHead.confidence`) below which the printed summary
counts a view as one the head is unsure of."""


def head_errors(checkpoint: str, cfg: FacingHeadConfig) -> tuple[np.ndarray, np.ndarray]:
    """Absolute angle error (degrees) of ``checkpoint``'s facing head on the views :func:`gather` draws, and the
    head's confidence on each."""
    session, records = dataset_session(checkpoint, cfg)
    head = session.pretrained.facing_head
    if head is None:
        raise DepthnerfError(f"{checkpoint}: carries no facing head (depthnerf fit-facing writes one)")
    pooled, psi, _ = gather(session, dataclasses.replace(cfg, grid=head.grid), records)  # pooled as the head was
    predicted, confidence = head.estimate(pooled)
    return angle_error(predicted.double(), psi).abs().numpy(), confidence.numpy()


def photo_errors(checkpoint: str, cfg: FacingHeadConfig) -> tuple[np.ndarray, np.ndarray]:
    """Absolute angle error (degrees) of ``checkpoint``'s facing head (without one: of the search's best plane,
    :func:`depthnerf.infer.facing.search_facing`) on the same views given to ``reconstruct`` as RGBA photos
    (``--photo``): each view is prepared as a photo is (recentred and scaled to the model's fill,
    :func:`depthnerf.prepare_photo`), its prior computed from it, and encoded from the photo camera at azimuth 0,
    where the true facing is ``90 - psi`` (:func:`depthnerf.data.symmetry.facing_from_relative`); and the head's
    confidence on each (NaN without a head)."""
    rec = Reconstructor.from_pretrained(checkpoint)
    if not rec.session.model.cfg.mirror:
        raise DepthnerfError(f"{checkpoint}: not a mirror model, so it has no plane to estimate")
    records = index_split(cfg.data, cfg.category, cfg.split).objects[: cfg.objects]
    plane, _ = dataset_plane(cfg.data, cfg.category)
    settings = ReconstructConfig(facing="auto", mesh_resolution=0)
    errors, confidence = [], []
    for record, picks in zip(records, drawn_views(records, cfg), strict=True):
        for view in picks:
            src = rec.session.load_views(record, [view], record.intrinsics.height)
            rgba = np.dstack([src.images[0].permute(1, 2, 0).numpy(), src.masks[0].numpy()])
            out = rec.reconstruct((rgba * 255).round().astype(np.uint8), views=1, config=settings)
            true = 90.0 - relative_facing(plane, src.poses[0].double().numpy())
            fit = out.settings["facing_fit"]
            estimate = fit["head"] if rec.has_facing_head else fit["best"]
            errors.append(abs(angle_error(float(estimate), true)))
            confidence.append(fit["head_confidence"] if rec.has_facing_head else float("nan"))
    return np.array(errors), np.array(confidence)


def summary(errors: np.ndarray, confidence: np.ndarray) -> dict[str, float]:
    """Median, 90th percentile and shares within 3 and 10 degrees of absolute errors; the share of views whose
    head confidence is below :data:`UNSURE` and the median error of those views and of the rest (None where there
    are none)."""
    unsure = confidence < UNSURE

    def median(e: np.ndarray) -> float | None:
        return float(np.median(e)) if e.size else None

    return {"views": int(errors.size), "median_deg": float(np.median(errors)),
            "p90_deg": float(np.quantile(errors, 0.9)), "within_3": float(np.mean(errors <= 3.0)),
            "within_10": float(np.mean(errors <= 10.0)), "unsure": float(np.mean(unsure)),
            "unsure_median_deg": median(errors[unsure]), "sure_median_deg": median(errors[~unsure])}


def degrees(value: float | None) -> str:
    """A median of :func:`summary` for printing (``-`` where there were no views)."""
    return "-" if value is None else f"{value:.1f}"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", nargs="+", required=True, help="checkpoints with a facing head")
    p.add_argument("--data", type=Path, required=True, help="dataset root")
    p.add_argument("--category", required=True, help="category folder prefix, e.g. chairs")
    p.add_argument("--split", choices=("train", "val", "test"), default="test", help="split (default test)")
    p.add_argument("--objects", type=int, default=20, help="at most N objects (default 20)")
    p.add_argument("--views-per-object", type=int, default=25, help="views drawn per object (default 25)")
    p.add_argument("--seed", type=int, default=0, help="seed of the view draw")
    p.add_argument("--inputs", choices=("dataset", "photo"), default="dataset",
                   help="encode each view as it is (default) or framed as a photo, as fit-facing --inputs does")
    p.add_argument("--photo", action="store_true", help="give each view to reconstruct as an RGBA photo (prepared "
                   "as photos are) instead of encoding it as a dataset view")
    p.add_argument("--json", type=Path, help="write the summaries here")
    args = p.parse_args(argv)
    if args.photo and args.inputs != "dataset":
        p.error("--photo gives each view to reconstruct, which frames it itself: drop --inputs")
    cfg = FacingHeadConfig(data=args.data, category=args.category, split=args.split, objects=args.objects,
                           views_per_object=args.views_per_object, seed=args.seed, inputs=args.inputs)
    results = {}
    try:
        with torch.no_grad():
            for ckpt in args.checkpoint:
                results[ckpt] = summary(*(photo_errors if args.photo else head_errors)(ckpt, cfg))
                r = results[ckpt]
                print(f"{ckpt}: {r['views']} views, |angle error| median {r['median_deg']:.2f} deg, 90th percentile "
                      f"{r['p90_deg']:.2f}, within 3 deg {r['within_3']:.0%}, within 10 deg {r['within_10']:.0%}; "
                      f"confidence below {UNSURE:g} in {r['unsure']:.0%} (|angle error| median "
                      f"{degrees(r['unsure_median_deg'])} there, {degrees(r['sure_median_deg'])} elsewhere)")
    except DepthnerfError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
