"""The conditioning stage: source images + masks + cameras (+ a prior source) -> the encoder's :class:`SourceViews`.

Every caller goes through here: training items, validation, and every inference path (through
:class:`~depthnerf.infer.InferenceSession`: ``depthnerf eval``, :class:`Reconstructor`, the demo, the app) and the
benchmarks. The prior source (:class:`~depthnerf.depth.prior.PriorSource`) serves raw relative disparity; it is
normalised over each view's foreground mask by :func:`normalized_disparity` (``normalize_disparity``) into
``SourceViews.disparity``, so every path feeds the encoder the same numbers for the same view.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from jaxtyping import Bool, Float
from torch import Tensor

from depthnerf.data.cameras import Intrinsics
from depthnerf.data.srn import ObjectViews
from depthnerf.depth.normalize import normalize_disparity
from depthnerf.depth.prior import DatasetViews, PriorSource
from depthnerf.model.pixelnerf import SourceViews


def normalized_disparity(disparity: Float[Tensor, "V H W"], masks: Bool[Tensor, "V H W"]
                         ) -> Float[Tensor, "V 1 H W"]:
    """The encoder's disparity channel of V views: raw disparity normalised over each view's mask."""
    return normalize_disparity(disparity, masks)[:, None]


@dataclass
class Conditioned:
    """What the encoder gets (B = 1) and the raw disparity it was made from."""

    inputs: SourceViews
    """Images, cameras and normalised disparity of the source views, on the device."""
    disparity: Float[Tensor, "V H W"] | None
    """Raw relative disparity the prior source served (None: no prior)."""


def condition(prior_source: PriorSource, images: Float[Tensor, "V 3 H W"], masks: Bool[Tensor, "V H W"],
              poses: Float[Tensor, "V 4 4"], intr: Intrinsics, device: torch.device | str = "cpu", *,
              depths: Float[Tensor, "V H W"] | None = None, where: DatasetViews | None = None,
              symmetry_plane: Sequence[float] | None = None) -> Conditioned:
    """The encoder input of V source views of one object (see the module docstring); ``symmetry_plane``: the
    object's mirror plane in the world frame (:mod:`depthnerf.data.symmetry`; None: none given)."""
    disparity = prior_source.disparity(images, depths=depths, where=where)
    normalized = None if disparity is None else normalized_disparity(disparity, masks)[None].to(device)
    plane = None if symmetry_plane is None else torch.tensor([list(symmetry_plane)], dtype=torch.float32,
                                                             device=device)
    return Conditioned(
        inputs=SourceViews(images=images[None].to(device), poses=poses[None].to(device),
                           focal=torch.tensor([intr.focal], device=device),
                           principal=torch.tensor([[intr.cx, intr.cy]], device=device), disparity=normalized,
                           symmetry_plane=plane),
        disparity=disparity)


def condition_views(prior_source: PriorSource, obj: ObjectViews, device: torch.device | str = "cpu", *,
                    symmetry_plane: Sequence[float] | None = None) -> Conditioned:
    """:func:`condition` on loaded dataset views (all of ``obj``'s views are sources)."""
    return condition(prior_source, obj.images, obj.masks, obj.poses, obj.intrinsics, device, depths=obj.depths,
                     where=DatasetViews(obj.record, tuple(int(v) for v in obj.view_indices.tolist())),
                     symmetry_plane=symmetry_plane)
