"""The depth prior's one road: a :class:`PriorConfig` names it, a :class:`PriorSource` serves its disparity.

``--depth NAME [--depth-checkpoint W]`` (every command) -> a :class:`PriorConfig`, named ``prior`` (stored in the
run config and in every checkpoint's inference spec; :meth:`PriorConfig.override` is the one rule for the flags)
-> :func:`open_prior` -> a :class:`PriorSource`, named ``prior_source`` -> ``prior_source.disparity(...)`` (raw
relative ``disparity`` ``[V, H, W]``) -> :func:`depthnerf.model.conditioning.condition` (normalised over the mask
into ``SourceViews.disparity``, the encoder's input). Whether the model is depth-aware is *derived* from the
config (:attr:`PriorConfig.enabled`), never stored beside it.

Sources
    ``cache``: the dataset's prior cache made by ``depthnerf depth`` (:class:`~depthnerf.depth.cache.PriorStore`;
    for ``oracle`` the dataset's ground-truth depth, read on the fly); serves dataset views only.
    ``live``: the estimator run on the given images (photos, the demo); ``match_cache=True`` rounds its output
    exactly as the cache stores it (:func:`~depthnerf.depth.cache.as_cached`), so a live prior equals the prior
    ``depthnerf eval`` reads for the same image. ``oracle`` runs live only on views that come with ground-truth
    depth.
    ``none``: no prior (the pixelNeRF baseline): ``disparity`` returns None.

Which weights a model was trained with is recorded twice: the prior's ``checkpoint`` (a name or a path, as given)
and the SHA-256 of the weights (``prior_weights_hash`` in a checkpoint's spec, ``weights_hash`` in a run's
``prior.json``). The hash decides: :func:`portable_prior` renames the weights to the shipped ones with that hash
(so a checkpoint trained on a file that has since shipped, or on a default that has since changed, reads the
same weights on any install), and :func:`weights_mismatch` is the check made where the prior is opened.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from jaxtyping import Float
from torch import Tensor

from depthnerf.data.records import ObjectRecord
from depthnerf.depth.cache import PriorStore, as_cached
from depthnerf.depth.estimators import ESTIMATORS, estimator_entry, make_estimator
from depthnerf.errors import DepthnerfError


@dataclass
class PriorConfig:
    """The frozen monocular depth prior fed to the depth-aware encoder (``--depth`` / ``--depth-checkpoint``)."""

    estimator: str = "bundled"
    """A name of the registry :data:`~depthnerf.depth.estimators.ESTIMATORS`: ``none`` (pixelNeRF baseline),
    ``bundled`` (offline default), ``oracle`` (ground truth), or ``depth-anything-v2`` (the paper's; needs a
    local checkpoint and a cache made by ``depthnerf depth``)."""
    checkpoint: str | None = None
    """Estimator weights (hub id or local directory) for ``depth-anything-v2``; a weights file for ``bundled``."""

    def __post_init__(self) -> None:
        if self.estimator not in ESTIMATORS:
            raise DepthnerfError(f"unknown depth prior {self.estimator!r}: choose {', '.join(ESTIMATORS)}")

    @property
    def enabled(self) -> bool:
        """The model is depth-aware (its encoder takes the prior): every estimator but ``none``."""
        return self.estimator != "none"

    def override(self, depth: str | None = None, depth_checkpoint: str | None = None) -> PriorConfig:
        """This prior with ``--depth`` / ``--depth-checkpoint`` applied, the one rule of every command: None keeps
        the estimator; the weights are ``depth_checkpoint`` when given, else this prior's own when the estimator
        is unchanged, else the new estimator's default (None)."""
        estimator = depth or self.estimator
        if depth_checkpoint is not None:
            return PriorConfig(estimator, depth_checkpoint)
        return PriorConfig(estimator, self.checkpoint if estimator == self.estimator else None)


@dataclass(frozen=True)
class DatasetViews:
    """Which dataset views a set of images are (what a cached prior is looked up by)."""

    record: ObjectRecord
    """The object's index record."""
    views: tuple[int, ...]
    """View indices of the object, in the images' order."""


class PriorSource:
    """Raw relative disparity ``[V, H, W]`` (float32, CPU) of source views, or None without a prior."""

    config: PriorConfig
    """The prior this source serves."""
    kind: str
    """``cache``, ``live`` or ``none``."""
    needs_depths: bool = False
    """:meth:`disparity` needs the views' ground-truth depth (the ``oracle`` prior run live)."""

    def disparity(self, images: Float[Tensor, "V 3 H W"], *, depths: Float[Tensor, "V H W"] | None = None,
                  where: DatasetViews | None = None) -> Float[Tensor, "V H W"] | None:
        """The prior of these views (``depths``: their ground-truth z-depth; ``where``: their dataset views)."""
        raise NotImplementedError

    def check(self, records: Sequence[ObjectRecord]) -> None:
        """Fail early (one line naming the fix) if any of these objects has no prior."""

    @property
    def provenance(self) -> dict[str, Any] | None:
        """JSON-able provenance (estimator, weights hash, ...), None without a prior."""
        return None


class NoPrior(PriorSource):
    """``none``: the baseline's encoder sees no prior."""

    kind = "none"

    def __init__(self, config: PriorConfig) -> None:
        self.config = config

    def disparity(self, images, *, depths=None, where=None):
        return None


class CachedPrior(PriorSource):
    """Priors from the dataset's cache (``depthnerf depth``), or ground truth on the fly for ``oracle``."""

    kind = "cache"

    def __init__(self, config: PriorConfig, store: PriorStore) -> None:
        self.config, self.store = config, store

    def disparity(self, images, *, depths=None, where=None):
        if where is None:
            raise DepthnerfError(f"the '{self.config.estimator}' prior cache serves dataset views only; "
                                 "open a live prior source for photos")
        return self.store.load(where.record, list(where.views))

    def check(self, records: Sequence[ObjectRecord]) -> None:
        self.store.check(records)

    @property
    def provenance(self) -> dict[str, Any]:
        return self.store.provenance


class LivePrior(PriorSource):
    """The estimator run on the images themselves (see the module docstring for ``match_cache``)."""

    kind = "live"

    def __init__(self, config: PriorConfig, device: str = "cpu", match_cache: bool = False) -> None:
        self.config, self.match_cache = config, match_cache
        self.estimator = make_estimator(config.estimator, config.checkpoint, device=device)
        self.needs_depths = self.estimator.needs_depth

    def disparity(self, images, *, depths=None, where=None):
        if self.estimator.needs_depth and depths is None:
            raise DepthnerfError("the 'oracle' depth prior needs ground-truth depth, which a photo does not have; "
                                 f"choose --depth {' or '.join(n for n in ESTIMATORS if estimator_entry(n).photo)}")
        disparity = self.estimator.predict(images, depths if self.estimator.needs_depth else None).float()
        return as_cached(disparity) if self.match_cache and estimator_entry(self.config.estimator).cached else disparity

    @property
    def provenance(self) -> dict[str, Any]:
        return self.estimator.provenance.as_dict()


def portable_prior(prior: PriorConfig, weights_hash: str | None) -> PriorConfig:
    """``prior`` with its weights named as shipped when ``weights_hash`` is a shipped file's of its estimator
    (:attr:`~depthnerf.depth.estimators.EstimatorEntry.shipped_name`); otherwise ``prior`` itself."""
    if not prior.enabled or not weights_hash:
        return prior
    name = estimator_entry(prior.estimator).shipped_name(weights_hash)
    return prior if name is None else PriorConfig(prior.estimator, name)


def weights_mismatch(prior_source: PriorSource, weights_hash: str | None, where: str) -> str | None:
    """One line saying that ``prior_source`` serves other weights than ``weights_hash`` (the weights a model or
    run was trained with, ``where``), or None when they agree or nothing was recorded."""
    served = (prior_source.provenance or {}).get("weights_hash")
    if not weights_hash or served is None or served == weights_hash:
        return None
    named = prior_source.config.checkpoint or "its default weights"
    return (f"{where}: trained on '{prior_source.config.estimator}' weights sha256 {weights_hash[:12]}..., but "
            f"{named} has sha256 {served[:12]}...")


def open_prior(prior: PriorConfig, *, data_root: str | os.PathLike | None = None, resolution: int = 128,
               records: Sequence[ObjectRecord] = (), device: str = "cpu", match_cache: bool = False) -> PriorSource:
    """The source of ``prior``: the dataset cache at ``resolution`` when ``data_root`` is given (checked for
    ``records``), else the live estimator on ``device``; :class:`NoPrior` for ``none``."""
    if not prior.enabled:
        return NoPrior(prior)
    if data_root is None:
        return LivePrior(prior, device, match_cache)
    store = PriorStore.open(Path(data_root), prior.estimator, prior.checkpoint, resolution=resolution)
    prior_source = CachedPrior(prior, store)
    prior_source.check(records)
    return prior_source
