"""Accuracy of a depth estimator on a dataset split (what ``depthnerf depth-eval`` runs).

Scores are AbsRel and delta<1.25 after per-image least-squares scale-and-shift alignment in disparity space on
the ground-truth foreground (:mod:`depthnerf.depth.metrics`), averaged over images. Predictions come from the
cache when a complete, up-to-date one exists for this estimator, weights and the dataset resolution, else the
estimator runs directly (the result says which).

Every result also carries the scores of a *flat* prediction (one constant disparity per image, which the
alignment turns into the image's mean foreground disparity) on the same images: the floor an estimator must
beat. On small objects far from the camera the flat prediction already scores well, so read an estimator's
AbsRel against it.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import torch
from tqdm import tqdm

from depthnerf.depth.cache import PriorStore, missing_depth
from depthnerf.depth.estimators import describe_estimator, make_estimator
from depthnerf.depth.metrics import affine_invariant_scores
from depthnerf.depth.precompute import predict_views
from depthnerf.errors import DepthnerfError


@dataclass
class DepthEvalConfig:
    """What ``depthnerf depth-eval`` evaluates."""

    data_root: Path
    """Dataset root (SRN layout, with ``depth/`` ground truth)."""
    estimator: str
    """Estimator name (``none`` is not evaluable)."""
    checkpoint: str | None = None
    """Hub id / directory / weights file (None: the estimator's default)."""
    split: str = "test"
    """Split to evaluate."""
    categories: tuple[str, ...] | None = None
    """Categories (None: every category found)."""
    max_objects: int | None = None
    """Evaluate at most this many objects per category (the first ones by id)."""
    max_views: int | None = None
    """Evaluate at most this many views per object, evenly spaced (None: all)."""
    batch_size: int = 16
    """Images per estimator call."""
    device: str = "cpu"
    """Torch device of the estimator."""
    use_cache: bool = True
    """Read predictions from a complete cache when one exists."""
    progress: bool = True
    """Show a tqdm progress bar on stderr."""


@dataclass
class DepthEvalResult:
    """Dataset-level scores (means over images) and where the predictions came from."""

    abs_rel: float
    """Mean over images of the per-image AbsRel."""
    delta1: float
    """Mean over images of the per-image delta<1.25 accuracy."""
    images: int
    """Images scored (images without foreground are not scored)."""
    objects: int
    """Objects evaluated."""
    source: str
    """``cache`` or ``estimator``."""
    provenance: dict[str, Any]
    """Estimator provenance."""
    per_category: dict[str, dict[str, float]] = field(default_factory=dict)
    """``{category: {"abs_rel", "delta1", "images"}}``."""
    flat_reference: dict[str, Any] = field(default_factory=dict)
    """Scores of a constant prediction on the same images: ``{"abs_rel", "delta1", "per_category"}``."""

    def as_dict(self) -> dict[str, Any]:
        return {"abs_rel": self.abs_rel, "delta1": self.delta1, "images": self.images, "objects": self.objects,
                "source": self.source, "provenance": self.provenance, "per_category": self.per_category,
                "flat_reference": self.flat_reference}


def _summarise(per_cat: dict[str, list[torch.Tensor]]) -> tuple[torch.Tensor, dict[str, dict[str, float]]]:
    """All scored rows ``(N, 2)`` (AbsRel, delta1) and the per-category means."""
    per_category = {}
    for category, rows in per_cat.items():
        cat_rows = torch.cat(rows)
        per_category[category] = {"abs_rel": float(cat_rows[:, 0].mean()), "delta1": float(cat_rows[:, 1].mean()),
                                  "images": int(cat_rows.shape[0])}
    return torch.cat([torch.cat(rows) for rows in per_cat.values()]), per_category


def _view_subset(num_views: int, max_views: int | None) -> list[int]:
    if max_views is None or max_views >= num_views:
        return list(range(num_views))
    if max_views <= 0:
        raise DepthnerfError(f"--max-views must be positive, got {max_views}")
    return sorted({round(i * (num_views - 1) / max(max_views - 1, 1)) for i in range(max_views)})


def evaluate_depth(cfg: DepthEvalConfig) -> DepthEvalResult:
    """Score ``cfg.estimator`` on ``cfg.split`` (see the module docstring)."""
    from depthnerf.data.card import INTEGER_CENTRED
    from depthnerf.data.srn import discover_categories, index_split, load_object

    for flag, value in (("--max-objects", cfg.max_objects), ("--max-views", cfg.max_views),
                        ("--batch-size", cfg.batch_size)):
        if value is not None and value <= 0:  # checked before any file is read or the estimator loads
            raise DepthnerfError(f"{flag} must be positive, got {value}")
    provenance = describe_estimator(cfg.estimator, cfg.checkpoint)
    if provenance is None:
        raise DepthnerfError("estimator 'none' produces no depth, there is nothing to evaluate")
    categories = list(cfg.categories) if cfg.categories else discover_categories(cfg.data_root)
    if not categories:  # a folder that holds no dataset: nothing to score (records[0] below)
        raise DepthnerfError(f"{cfg.data_root}: no <category>_<split> folders found")
    records = []
    for category in categories:
        objects = index_split(cfg.data_root, category, cfg.split, check_files=False).objects
        records.extend(objects[: cfg.max_objects] if cfg.max_objects else objects)
    for record in records:
        if not record.has_depth:
            raise DepthnerfError(f"{record.path}: depth-eval needs ground-truth z-depth, {missing_depth(record)}")
    resolution = records[0].intrinsics.height
    same_size = all(r.intrinsics.height == resolution for r in records)
    store = None
    if cfg.use_cache and same_size and cfg.estimator != "oracle":
        try:
            store = PriorStore.open(cfg.data_root, cfg.estimator, cfg.checkpoint, resolution=resolution)
            store.check(records)
        except DepthnerfError:
            store = None
    estimator = None if store is not None else make_estimator(cfg.estimator, cfg.checkpoint, device=cfg.device)
    per_cat: dict[str, list[torch.Tensor]] = {}
    flat_cat: dict[str, list[torch.Tensor]] = {}
    bar = tqdm(records, desc=f"depth-eval ({cfg.estimator})", unit="obj", file=sys.stderr,
               disable=not cfg.progress)
    for record in bar:
        views = _view_subset(record.num_views, cfg.max_views)
        # pixels and depth only: masks are never read (the foreground is depth > 0)
        obj = load_object(replace(record, has_mask=False), views, with_depth=True,
                          pixel_center=INTEGER_CENTRED)
        if store is not None:
            disparity = store.load(record, views)
        else:
            disparity = predict_views(estimator, obj.images, obj.depths, cfg.batch_size)
        for sink, pred in ((per_cat, disparity), (flat_cat, torch.ones_like(obj.depths))):
            scores = affine_invariant_scores(pred, obj.depths)
            sink.setdefault(record.category, []).append(
                torch.stack([scores.abs_rel, scores.delta1], dim=1)[scores.valid])
    all_rows, per_category = _summarise(per_cat)
    if all_rows.shape[0] == 0:
        raise DepthnerfError(f"{cfg.data_root}: no evaluated image has any foreground depth")
    flat_rows, flat_per_category = _summarise(flat_cat)
    flat = {"abs_rel": float(flat_rows[:, 0].mean()), "delta1": float(flat_rows[:, 1].mean()),
            "per_category": {c: {k: v for k, v in d.items() if k != "images"} for c, d in flat_per_category.items()}}
    return DepthEvalResult(abs_rel=float(all_rows[:, 0].mean()), delta1=float(all_rows[:, 1].mean()),
                           images=int(all_rows.shape[0]), objects=len(records),
                           source="cache" if store is not None else "estimator",
                           provenance={**provenance.as_dict(), "resolution": resolution},
                           per_category=per_category, flat_reference=flat)
