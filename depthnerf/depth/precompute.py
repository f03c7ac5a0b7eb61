"""Filling the depth-prior cache (what ``depthnerf depth`` runs); layout and keys in :mod:`depthnerf.depth.cache`.

Every object of every requested ``<category>_<split>`` gets one file with the raw disparity of all its views at
the requested resolution (default: the dataset's own). The run is resumable: an object whose file exists with
the same weights hash, resolution and source fingerprint, and is sound (the tensor, its shape and every value
finite: :func:`~depthnerf.depth.cache.object_file_problem`), is skipped; a stale or damaged one is recomputed.
The manifest records the provenance and, per ``<category>_<split>``, how many objects are done.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch
from tqdm import tqdm

from depthnerf import __version__
from depthnerf.depth.cache import (
    cache_dir,
    fingerprint_matches,
    is_bytes_fingerprint,
    object_file_problem,
    object_path,
    read_object_metadata,
    rgb_fingerprint,
    write_object_priors,
)
from depthnerf.depth.estimators import CACHED_ESTIMATORS, DepthEstimator, describe_estimator, make_estimator
from depthnerf.errors import DepthnerfError
from depthnerf.files import write_json_atomic

MIN_RESOLUTION = 8
"""The least ``--resolution`` priors are cached at: the least image side training and eval take
(``data.resolution`` of ``depthnerf.train.config.NUMBER_RULES``)."""


@dataclass
class PrecomputeConfig:
    """What ``depthnerf depth`` computes."""

    data_root: Path
    """Dataset root (SRN layout)."""
    estimator: str
    """A cached estimator name (``depth-anything-v2`` or ``bundled``)."""
    checkpoint: str | None = None
    """Hub id / directory / weights file (None: the estimator's default)."""
    splits: tuple[str, ...] = ("train", "val", "test")
    """Splits to process."""
    categories: tuple[str, ...] | None = None
    """Categories to process (None: every category found under ``data_root``)."""
    require_splits: bool = False
    """A missing ``<category>_<split>`` folder is an error (else it is reported and skipped)."""
    batch_size: int = 16
    """Images per estimator call."""
    resolution: int | None = None
    """Image side to compute priors at (None: the dataset's own resolution)."""
    device: str = "cpu"
    """Torch device of the estimator."""
    progress: bool = True
    """Show a tqdm progress bar on stderr."""


@dataclass
class PrecomputeSummary:
    """What a precompute run did."""

    cache_dir: Path
    """The cache folder written."""
    computed: int = 0
    """Objects computed in this run."""
    skipped: int = 0
    """Objects already up to date."""
    stale: int = 0
    """Objects recomputed because their cached file was stale or from other weights."""
    damaged: list[str] = field(default_factory=list)
    """``<path>: <problem>`` of each object recomputed because its cached file was unreadable or damaged (no
    ``disparity`` tensor, another shape or view count, non-finite values)."""
    missing_splits: list[str] = field(default_factory=list)
    """``<category>_<split>`` folders that do not exist (skipped)."""


def _records(cfg: PrecomputeConfig, summary_missing: list[str]) -> list:
    from depthnerf.data.srn import discover_categories, index_split, split_dir

    categories = list(cfg.categories) if cfg.categories else discover_categories(cfg.data_root)
    if not categories:
        raise DepthnerfError(f"{cfg.data_root}: no <category>_<split> folders found")
    records = []
    for category in categories:
        present = [s for s in cfg.splits if split_dir(cfg.data_root, category, s).is_dir()]
        if cfg.categories and not present and not cfg.require_splits:  # a named category with nothing: a typo?
            found = ", ".join(discover_categories(cfg.data_root)) or "none"
            raise DepthnerfError(f"{cfg.data_root}: --category {category}: no {category}_<split> folder "
                                 f"({', '.join(cfg.splits)}) exists here (categories here: {found})")
        for split in cfg.splits:
            if split not in present:
                if cfg.require_splits:
                    raise DepthnerfError(f"{split_dir(cfg.data_root, category, split)}: split folder does not exist")
                summary_missing.append(f"{category}_{split}")
                continue
            records.extend(index_split(cfg.data_root, category, split, check_files=False).objects)
    if not records:
        raise DepthnerfError(f"{cfg.data_root}: none of the requested splits exist ({', '.join(cfg.splits)})")
    return records


def _check_counts(cfg: PrecomputeConfig) -> None:
    if cfg.batch_size <= 0:
        raise DepthnerfError(f"--batch-size must be positive, got {cfg.batch_size}")
    if cfg.resolution is not None and cfg.resolution < MIN_RESOLUTION:
        raise DepthnerfError(f"--resolution must be >= {MIN_RESOLUTION}, got {cfg.resolution}")


def requested_records(cfg: PrecomputeConfig) -> list:
    """The objects ``cfg`` asks for, checked as :func:`precompute_priors` checks them (one line for a
    ``--batch-size`` or ``--resolution`` that cannot work, a folder without datasets, a category or split that is
    not there), whichever estimator ``cfg`` names: ``depthnerf depth`` checks the request of one without a cache
    with it. Reads the split indexes only."""
    _check_counts(cfg)
    return _records(cfg, [])


def _resolution(cfg: PrecomputeConfig, records: list) -> int:
    if cfg.resolution is not None:
        return cfg.resolution
    sizes = {(r.intrinsics.height, r.intrinsics.width) for r in records}
    if len(sizes) > 1:
        raise DepthnerfError(f"{cfg.data_root}: objects have different image sizes {sorted(sizes)}; "
                             "pass --resolution")
    return next(iter(sizes))[0]


def predict_views(estimator: DepthEstimator, images: torch.Tensor, depths: torch.Tensor | None,
                  batch_size: int) -> torch.Tensor:
    """Run an estimator over ``[V, 3, H, W]`` images in batches; ``[V, H, W]`` float32 disparity."""
    outs = []
    for start in range(0, images.shape[0], batch_size):
        stop = start + batch_size
        outs.append(estimator.predict(images[start:stop], None if depths is None else depths[start:stop]))
    return torch.cat(outs).float()


def precompute_priors(cfg: PrecomputeConfig) -> PrecomputeSummary:
    """Fill the cache for ``cfg`` (resumable; see the module docstring)."""
    from depthnerf.data.card import INTEGER_CENTRED
    from depthnerf.data.srn import load_object

    if cfg.estimator not in CACHED_ESTIMATORS:
        raise DepthnerfError(f"estimator '{cfg.estimator}' is not cached (cached: {', '.join(CACHED_ESTIMATORS)})")
    _check_counts(cfg)
    provenance = describe_estimator(cfg.estimator, cfg.checkpoint)
    assert provenance is not None
    missing: list[str] = []
    records = _records(cfg, missing)
    resolution = _resolution(cfg, records)
    root = cache_dir(cfg.data_root, provenance, resolution)
    summary = PrecomputeSummary(cache_dir=root, missing_splits=missing)
    manifest_path = root / "manifest.json"
    manifest = {"provenance": provenance.as_dict(), "resolution": resolution, "depthnerf": __version__,
                "fingerprint": "sha256 of view names + RGB file bytes", "splits": {}}
    if manifest_path.is_file():
        import json

        try:
            old = json.loads(manifest_path.read_text())
        except (OSError, ValueError):
            old = {}
        if old.get("provenance", {}).get("weights_hash") not in (None, provenance.weights_hash):
            raise DepthnerfError(f"{manifest_path}: folder holds priors of other weights; remove it first")
        manifest["splits"] = dict(old.get("splits", {}))

    estimator: DepthEstimator | None = None
    done: dict[str, int] = {}
    totals: dict[str, int] = {}
    bar = tqdm(records, desc=f"depth priors ({cfg.estimator})", unit="obj", file=sys.stderr,
               disable=not cfg.progress)
    for record in bar:
        group = f"{record.category}_{record.split}"
        totals[group] = totals.get(group, 0) + 1
        path = object_path(root, record)
        meta = read_object_metadata(path)
        stored = None if meta is None else meta.get("fingerprint")
        # the full-bytes fingerprint only where the entry's scheme compares it, or when an entry is (re)written
        fingerprint = rgb_fingerprint(record) if is_bytes_fingerprint(stored) else None
        current = meta is not None and fingerprint_matches(stored, record, fingerprint) and (
            meta.get("weights_hash"), meta.get("resolution")) == (provenance.weights_hash, str(resolution))
        problem = object_file_problem(path, record, resolution) if current or (
            meta is None and path.exists()) else None
        if current and problem is None:
            summary.skipped += 1
        else:
            if problem is not None:
                summary.damaged.append(f"{path}: {problem}")
            else:
                summary.stale += meta is not None
            fingerprint = fingerprint or rgb_fingerprint(record)
            if estimator is None:  # loaded (and the manifest written) only once there is work to do
                estimator = make_estimator(cfg.estimator, cfg.checkpoint, device=cfg.device)
                write_json_atomic(manifest_path, manifest)
            # pixels only: masks are never read, so a bad optional mask/ (a warning elsewhere) cannot stop this
            views = load_object(replace(record, has_mask=False), resolution=resolution,
                                pixel_center=INTEGER_CENTRED)
            disparity = predict_views(estimator, views.images, None, cfg.batch_size)
            write_object_priors(path, disparity, {
                "fingerprint": fingerprint, "weights_hash": provenance.weights_hash,
                "estimator": provenance.estimator, "resolution": str(resolution),
                "views": str(len(record.view_names)), "object_id": record.object_id})
            summary.computed += 1
        done[group] = done.get(group, 0) + 1
        bar.set_postfix(computed=summary.computed, skipped=summary.skipped)
    for group, count in totals.items():
        manifest["splits"][group] = {"objects": count, "complete": done.get(group, 0) == count}
    write_json_atomic(manifest_path, manifest)
    return summary
