"""``depthnerf depth-eval``: affine-invariant accuracy of a depth estimator against ground-truth z-depth.

``depthnerf depth-eval --data DIR [--split test] --depth NAME [--depth-checkpoint W] [--category C]
[--json PATH] [--max-objects N] [--max-views N]`` (``--estimator`` / ``--checkpoint``: older spellings of
``--depth`` / ``--depth-checkpoint``, kept as aliases)

Prints AbsRel and delta<1.25 after per-image least-squares scale-and-shift alignment in disparity space on the
foreground (:mod:`depthnerf.depth.metrics`), overall and per category. ``--json`` writes
``{"abs_rel", "delta1", "images", "objects", "source", "provenance", "per_category", "flat_reference"}``; the
last line of the report (and ``flat_reference``) scores a constant prediction on the same images, the floor any
estimator must beat. Uses the cache when a
complete one exists (``--no-cache`` to always run the estimator).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from depthnerf.depth.bundled import shipped_nets_text
from depthnerf.depth.estimators import ESTIMATORS
from depthnerf.depth.evaluate import DepthEvalConfig, evaluate_depth
from depthnerf.errors import DepthnerfError
from depthnerf.files import file_problem, write_text_atomic


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", type=Path, required=True, help="dataset root holding <category>_<split>/ folders")
    parser.add_argument("--split", choices=("train", "val", "test"), default="test", help="split (default test)")
    parser.add_argument("--depth", "--estimator", dest="depth", choices=ESTIMATORS, required=True,
                        help="depth prior (estimator) to score (--estimator: an older spelling, kept as an alias)")
    parser.add_argument("--depth-checkpoint", "--checkpoint", dest="depth_checkpoint", default=None,
                        help="estimator weights: hub id / local directory / shipped net's name (bundled: "
                             f"{shipped_nets_text()}) / weights file (--checkpoint: an older spelling, kept as an alias; it names "
                             "the estimator's weights, never a model)")
    parser.add_argument("--category", action="append", default=None, help="only this category (repeatable)")
    parser.add_argument("--json", type=Path, default=None, help="write the scores as JSON to this file")
    parser.add_argument("--max-objects", type=int, default=None, help="at most N objects per category")
    parser.add_argument("--max-views", type=int, default=None, help="at most N evenly spaced views per object")
    parser.add_argument("--batch-size", type=int, default=16, help="images per estimator call (default 16)")
    parser.add_argument("--device", default="cpu", help="torch device: cpu (default), cuda, cuda:N or auto")
    parser.add_argument("--no-cache", action="store_true", help="always run the estimator, ignore any cache")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from depthnerf.distributed import pick_device

    device = pick_device(args.device)  # a device this process lacks: one line, before any work
    if args.json is not None:  # found before the estimator runs, not after
        if args.json.is_dir():
            raise DepthnerfError(f"{args.json}: --json names a folder; give the path of the JSON file to write")
        if (problem := file_problem(args.json, "--json")) is not None:
            raise DepthnerfError(problem)
    cfg = DepthEvalConfig(
        data_root=args.data, estimator=args.depth, checkpoint=args.depth_checkpoint, split=args.split,
        categories=tuple(args.category) if args.category else None, max_objects=args.max_objects,
        max_views=args.max_views, batch_size=args.batch_size, device=str(device), use_cache=not args.no_cache,
        progress=not args.no_progress)
    result = evaluate_depth(cfg)
    print(f"{args.depth} on {args.split} ({result.objects} objects, {result.images} images, "
          f"predictions from {result.source}):")
    print(f"  all      AbsRel {result.abs_rel:.4f}  delta<1.25 {result.delta1:.4f}")
    for category, scores in sorted(result.per_category.items()):
        print(f"  {category:8s} AbsRel {scores['abs_rel']:.4f}  delta<1.25 {scores['delta1']:.4f}  "
              f"({scores['images']} images)")
    flat = result.flat_reference
    print(f"  flat     AbsRel {flat['abs_rel']:.4f}  delta<1.25 {flat['delta1']:.4f}  "
          "(a constant prediction on the same images: the floor to beat)")
    if args.json is not None:
        try:
            write_text_atomic(args.json, json.dumps(result.as_dict(), indent=2) + "\n")
        except OSError as err:
            raise DepthnerfError(f"{args.json}: cannot write the scores ({err.strerror or err})") from None
    return 0
