"""The ONE registry of depth-prior names (``--depth`` / ``--estimator`` everywhere), and loading by name.

Convention (all backends): RGB images ``[B, 3, H, W]`` in [0, 1] in, *relative disparity* ``[B, H, W]`` out at
the input's resolution: larger = closer, defined up to an unknown positive scale and a shift (see
``depthnerf/data/cameras.py`` for z-depth vs disparity). The network input is made from it by
:func:`depthnerf.depth.normalize.normalize_disparity`, identically for every backend.

Backends (``ESTIMATORS``):

``depth-anything-v2``
    Depth Anything V2 through ``transformers`` (:mod:`depthnerf.depth.depth_anything`); checkpoint = hub id or
    local directory, default ``depth-anything/Depth-Anything-V2-Base-hf`` (the paper's).
``bundled``
    The project's small U-Net shipped in ``depthnerf/depth/weights`` (:mod:`depthnerf.depth.bundled`); the
    offline default. Checkpoint = a shipped net's name (``srn``, the default; ``legacy``) or a weights file.
``oracle``
    Ground truth: ``1 / z`` on the foreground and 0 on the background, from the dataset's ``depth/`` z-maps. It
    needs the depths (``needs_depth``), so it cannot run on a bare photo.
``none``
    No prior at all (plain pixelNeRF): :func:`make_estimator` and :func:`describe_estimator` return ``None``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from depthnerf.depth.backend import (
    DepthEstimator,
    FrozenNetworkEstimator,
    OracleEstimator,
    PriorProvenance,
    oracle_disparity,
    oracle_provenance,
)
from depthnerf.depth.bundled import BundledEstimator, bundled_provenance, shipped_net_named_by_hash
from depthnerf.depth.depth_anything import DepthAnythingEstimator, depth_anything_provenance
from depthnerf.errors import DepthnerfError

__all__ = ["ESTIMATORS", "CACHED_ESTIMATORS", "PHOTO_ESTIMATORS", "EstimatorEntry", "estimator_entry",
           "describe_estimator", "make_estimator", "DepthEstimator", "FrozenNetworkEstimator", "OracleEstimator",
           "PriorProvenance", "oracle_disparity", "oracle_provenance"]


@dataclass(frozen=True)
class EstimatorEntry:
    """One depth-prior name and what it can do."""

    name: str
    """The name (``--depth NAME``)."""
    cached: bool
    """Priors are precomputed into the dataset's cache by ``depthnerf depth`` (else computed on the fly)."""
    photo: bool
    """Runs on a bare photo (``oracle`` needs ground-truth depth; ``none`` has nothing to run)."""
    describe: Callable[[str | None], PriorProvenance | None]
    """Provenance without loading the network (hashes the weights)."""
    load: Callable[[str | None, str], DepthEstimator | None]
    """``load(checkpoint, device)``: the frozen estimator."""
    shipped_name: Callable[[str], str | None] = lambda weights_hash: None
    """The name of the shipped weights with this SHA-256 (a ``--depth-checkpoint`` that works on any install),
    None when none ships (``bundled``: :func:`~depthnerf.depth.bundled.shipped_net_named_by_hash`)."""


_REGISTRY = (
    EstimatorEntry("depth-anything-v2", cached=True, photo=True, describe=depth_anything_provenance,
                   load=lambda ckpt, device: DepthAnythingEstimator.load(ckpt, device=device)),
    EstimatorEntry("bundled", cached=True, photo=True, describe=bundled_provenance,
                   load=lambda ckpt, device: BundledEstimator.load(ckpt, device=device),
                   shipped_name=shipped_net_named_by_hash),
    EstimatorEntry("oracle", cached=False, photo=False, describe=lambda ckpt: oracle_provenance(),
                   load=lambda ckpt, device: OracleEstimator()),
    EstimatorEntry("none", cached=False, photo=False, describe=lambda ckpt: None, load=lambda ckpt, device: None),
)

ESTIMATORS: tuple[str, ...] = tuple(e.name for e in _REGISTRY)
"""Every depth-prior name accepted by :func:`make_estimator`, the configs and the CLI."""

CACHED_ESTIMATORS: tuple[str, ...] = tuple(e.name for e in _REGISTRY if e.cached)
"""Estimators whose priors are precomputed by ``depthnerf depth`` (``oracle`` is computed on the fly)."""

PHOTO_ESTIMATORS: tuple[str, ...] = tuple(e.name for e in _REGISTRY if e.photo)
"""Estimators that run on a bare photo (``depthnerf reconstruct --depth``)."""


def estimator_entry(name: str) -> EstimatorEntry:
    """The registry entry of ``name``; an unknown name is a one-line error listing the known ones."""
    for entry in _REGISTRY:
        if entry.name == name:
            return entry
    raise DepthnerfError(f"unknown depth estimator '{name}' (choose from {', '.join(ESTIMATORS)})")


def describe_estimator(name: str, checkpoint: str | None = None) -> PriorProvenance | None:
    """Provenance of an estimator *without* loading its network (hashes the weights); None for ``none``."""
    return estimator_entry(name).describe(checkpoint)


def make_estimator(name: str, checkpoint: str | None = None, device: str = "cpu") -> DepthEstimator | None:
    """Load a frozen estimator by name (``checkpoint``: hub id / directory / weights file); None for ``none``."""
    return estimator_entry(name).load(checkpoint, device)
