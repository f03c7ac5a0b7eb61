"""``depthnerf depth``: precompute monocular depth priors into the dataset's cache.

``depthnerf depth --data DIR --depth {bundled,depth-anything-v2} [--depth-checkpoint WEIGHTS]
[--splits train val test] [--category C] [--batch-size N] [--resolution R] [--device cpu] [--strict]``
(``--estimator`` / ``--checkpoint``: older spellings of ``--depth`` / ``--depth-checkpoint``, kept as aliases), or
``depthnerf depth --data DIR --for CHECKPOINT [...]``: the prior that checkpoint reads (what
``depthnerf eval --checkpoint CHECKPOINT`` needs).

Writes ``DIR/depth_priors/<estimator>-<hash12>-<res>/<category>_<split>/<object_id>.safetensors`` plus a
``manifest.json`` (see :mod:`depthnerf.depth.cache`); resumable (finished objects are skipped), atomic writes.
``oracle`` and ``none`` need no cache: the command checks the request as for a cached estimator (the data
folder, ``--category``, ``--splits``, the counts), says so and exits 0.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from depthnerf.depth.bundled import shipped_nets_text
from depthnerf.depth.estimators import CACHED_ESTIMATORS, ESTIMATORS
from depthnerf.depth.precompute import PrecomputeConfig, precompute_priors, requested_records

DEFAULT_SPLITS = ("train", "val", "test")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", type=Path, required=True, help="dataset root holding <category>_<split>/ folders")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--depth", "--estimator", dest="depth", choices=ESTIMATORS,
                        help="depth prior (estimator) to cache (--estimator: an older spelling, kept as an alias)")
    source.add_argument("--for", dest="for_checkpoint", metavar="CHECKPOINT", default=None,
                        help="cache the prior this checkpoint reads (shipped name, weights file or run folder): its "
                             "estimator and weights, at its resolution unless --resolution says otherwise")
    parser.add_argument("--depth-checkpoint", "--checkpoint", dest="depth_checkpoint", default=None,
                        help="estimator weights: hub id or local directory (depth-anything-v2), shipped net's "
                             f"name or weights file (bundled: {shipped_nets_text()}); default: the backend's default "
                             "(--checkpoint: an older spelling, kept as an alias; it names the estimator's weights, "
                             "never a model)")
    parser.add_argument("--splits", nargs="+", choices=DEFAULT_SPLITS, default=None,
                        help="splits to process (default: train val test, those that exist)")
    parser.add_argument("--category", action="append", default=None,
                        help="only this category (repeatable; default: every one found)")
    parser.add_argument("--batch-size", type=int, default=16, help="images per estimator call (default 16)")
    parser.add_argument("--resolution", type=int, default=None,
                        help="image side to compute priors at (default: the dataset's own)")
    parser.add_argument("--device", default="cpu", help="torch device: cpu (default), cuda, cuda:N or auto")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--strict", action="store_true",
                        help="check every file of the splits first; a problem in an optional part is an error too")


def _prior_of_checkpoint(args: argparse.Namespace) -> None:
    """``--for CHECKPOINT``: the estimator, weights and resolution come from the checkpoint's spec."""
    from depthnerf.errors import DepthnerfError
    from depthnerf.pretrained.load import load_pretrained

    if args.depth_checkpoint is not None:
        raise DepthnerfError("--for takes the weights from the checkpoint; drop --depth-checkpoint")
    spec = load_pretrained(args.for_checkpoint).spec
    args.depth, args.depth_checkpoint = spec.prior.estimator, spec.prior.checkpoint
    if args.resolution is None:  # a given one (0 too) is kept, and checked with the other counts
        args.resolution = spec.resolution


def run(args: argparse.Namespace) -> int:
    from depthnerf.distributed import pick_device

    device = pick_device(args.device)  # a device this process lacks: one line, before any work
    if args.for_checkpoint is not None:
        _prior_of_checkpoint(args)
    cfg = PrecomputeConfig(
        data_root=args.data, estimator=args.depth, checkpoint=args.depth_checkpoint,
        splits=tuple(args.splits or DEFAULT_SPLITS), categories=tuple(args.category) if args.category else None,
        require_splits=args.splits is not None, batch_size=args.batch_size, resolution=args.resolution,
        device=str(device), progress=not args.no_progress)
    if args.depth not in CACHED_ESTIMATORS:
        requested_records(cfg)  # nothing to cache, but a request that could not work is still one line
        print(f"estimator '{args.depth}' needs no cache "
              f"({'computed from depth/ on the fly' if args.depth == 'oracle' else 'no depth prior'})")
        return 0
    if args.strict:
        from depthnerf.data.srn import discover_categories, index_split, split_dir

        for category in args.category or discover_categories(args.data):
            for split in args.splits or DEFAULT_SPLITS:
                if args.splits or split_dir(args.data, category, split).is_dir():
                    index_split(args.data, category, split, strict=True)
    summary = precompute_priors(cfg)
    for group in summary.missing_splits:
        print(f"note: {group} does not exist under {args.data}, skipped")
    for line in summary.damaged:
        print(f"note: {line}; recomputed")
    damaged = f", {len(summary.damaged)} were unreadable or damaged" if summary.damaged else ""
    print(f"{summary.cache_dir}: {summary.computed} objects computed ({summary.stale} were stale{damaged}), "
          f"{summary.skipped} already up to date")
    return 0
