"""One object as every evaluation path prepares it: SRN protocol views, the input view's prior, its encoding.

``depthnerf eval`` (:mod:`depthnerf.eval.protocol`), ``depthnerf demo``, the guided-sampling benchmark and the
mesh diagnostics all go through :func:`prepare_object`, so an object is conditioned the same way everywhere: view
:data:`INPUT_VIEW` loaded at the training resolution, its raw disparity prior from a :data:`PriorFn` (the
depth-prior cache for evaluation, the estimator on the fly for the demo), both encoded once.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import torch

from depthnerf.data.srn import ObjectRecord, ObjectViews, load_object
from depthnerf.depth.cache import PriorStore
from depthnerf.errors import DepthnerfError
from depthnerf.eval.pretrained import Pretrained
from depthnerf.model.conditioning import source_views
from depthnerf.model.pixelnerf import EncodedViews, PixelNeRF, SourceViews

INPUT_VIEW = 64
"""The SRN protocol's input view."""
SRN_VIEWS = 251
"""Views per object of the SRN val/test sets."""


@dataclass(frozen=True)
class ProtocolViews:
    """Input and target view indices of one object."""

    input_view: int
    """The view the model is conditioned on."""
    targets: tuple[int, ...]
    """Scored views, in index order."""
    others: int
    """Number of views other than the input (targets before the stride)."""


def protocol_views(num_views: int, stride: int = 1) -> ProtocolViews:
    """View 64 as input (view 0 with <= 64 views), every ``stride``-th other view as a target."""
    if stride < 1:
        raise DepthnerfError(f"--views-stride must be >= 1, got {stride}")
    if num_views < 2:
        raise DepthnerfError(f"an object needs at least 2 views (an input and a target), has {num_views}")
    src = INPUT_VIEW if num_views > INPUT_VIEW else 0
    others = [v for v in range(num_views) if v != src]
    return ProtocolViews(input_view=src, targets=tuple(others[::stride]), others=len(others))


@dataclass
class PreparedObject:
    """One object as every evaluation path prepares it: the input view encoded once, the target views loaded."""

    views: ProtocolViews
    """Input and target view indices."""
    source: ObjectViews
    """The input view at the training resolution."""
    targets: ObjectViews
    """The target views at the evaluated resolution."""
    prior: torch.Tensor | None
    """[1 H W] raw depth prior of the input view (None for the baseline)."""
    inputs: SourceViews
    """What was encoded (the input view with its normalised prior, on the device)."""
    enc: EncodedViews
    """The model's features of the input view (and its prior)."""


def open_prior_store(pre: Pretrained, data_root: Path, records: Sequence[ObjectRecord],
                     depth_checkpoint: str | None = None) -> PriorStore | None:
    """The checkpoint's depth-prior store at its training resolution, checked for ``records``; None: no prior."""
    store = PriorStore.open(data_root, pre.config.prior.estimator, depth_checkpoint or pre.config.prior.checkpoint,
                            resolution=pre.config.data.resolution)
    if store is not None:
        store.check(records)
    return store


PriorFn = Callable[[ObjectViews], "torch.Tensor | None"]
"""The raw disparity prior ``[V H W]`` of loaded source views (None: no prior, the baseline)."""


def cached_prior(store: PriorStore | None) -> PriorFn:
    """The prior read from the depth-prior cache (``depthnerf depth``); no prior when ``store`` is None."""
    def prior(src: ObjectViews) -> torch.Tensor | None:
        return None if store is None else store.load(src.record, src.view_indices.tolist())
    return prior


@torch.no_grad()
def prepare_object(model: PixelNeRF, record: ObjectRecord, views: ProtocolViews, prior: PriorFn,
                   input_res: int, eval_res: int, device: torch.device, *,
                   source_depth: bool = False, pixel_center: float = 0.0) -> PreparedObject:
    """Load the input view at ``input_res`` (with its ground-truth depth when ``source_depth``), compute its
    ``prior`` and encode both; load the targets at ``eval_res``. ``pixel_center``: the data's pixel-centre
    convention as the model reads it (the checkpoint's ``data.pixel_center``)."""
    src = load_object(record, [views.input_view], resolution=input_res, with_depth=source_depth,
                      pixel_center=pixel_center)
    tgt = load_object(record, list(views.targets), resolution=eval_res, pixel_center=pixel_center)
    disp = prior(src)
    inputs = source_views(src, [0], disp, device)
    return PreparedObject(views=views, source=src, targets=tgt, prior=disp, inputs=inputs, enc=model.encode(inputs))
