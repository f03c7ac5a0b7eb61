"""One object as every evaluation path prepares it: SRN protocol views, the input view conditioned and encoded.

``depthnerf eval`` (:mod:`depthnerf.eval.protocol`), the guided-sampling benchmark and the mesh diagnostics go
through :func:`prepare_object`, so an object is conditioned the same way everywhere: view
:data:`~depthnerf.data.protocol.INPUT_VIEW` loaded at the training resolution, its prior from a
:class:`~depthnerf.depth.prior.PriorSource` (the depth-prior cache for evaluation), both through the conditioning
stage (:func:`~depthnerf.model.conditioning.condition_views`) and encoded once.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch

from depthnerf.data.protocol import INPUT_VIEW, SRN_VIEWS, ProtocolViews, protocol_views
from depthnerf.data.srn import ObjectRecord, ObjectViews, load_object
from depthnerf.depth.prior import PriorConfig, PriorSource, open_prior
from depthnerf.model.conditioning import condition_views
from depthnerf.model.pixelnerf import EncodedViews, PixelNeRF, SourceViews
from depthnerf.pretrained.spec import InferenceSpec

__all__ = ["INPUT_VIEW", "SRN_VIEWS", "ProtocolViews", "protocol_views", "PreparedObject", "dataset_prior",
           "prepare_object"]


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


def dataset_prior(spec: InferenceSpec, data_root: Path, records: Sequence[ObjectRecord],
                  prior: PriorConfig | None = None) -> PriorSource:
    """The checkpoint's prior (or ``prior``) from the dataset's cache at its training resolution, checked for
    ``records``."""
    return open_prior(prior or spec.prior, data_root=data_root, resolution=spec.resolution, records=records)


@torch.no_grad()
def prepare_object(model: PixelNeRF, record: ObjectRecord, views: ProtocolViews, prior: PriorSource,
                   input_res: int, eval_res: int, device: torch.device, *,
                   pixel_center: float = 0.0) -> PreparedObject:
    """Load the input view at ``input_res`` (with its ground-truth depth when the prior needs it), condition it
    on ``prior`` and encode it; load the targets at ``eval_res``. ``pixel_center``: the data's pixel-centre
    convention as the model reads it (the checkpoint's ``InferenceSpec.pixel_center``)."""
    src = load_object(record, [views.input_view], resolution=input_res,
                      with_depth=prior.needs_depths, pixel_center=pixel_center)
    tgt = load_object(record, list(views.targets), resolution=eval_res, pixel_center=pixel_center)
    cond = condition_views(prior, src, device)
    return PreparedObject(views=views, source=src, targets=tgt, prior=cond.disparity, inputs=cond.inputs,
                          enc=model.encode(cond.inputs))
