"""From loaded dataset views (and their depth prior) to the model's :class:`SourceViews` input.

Shared by training validation, SRN-protocol evaluation and reconstruction, so every caller normalises the prior
the same way (``depthnerf.depth.normalize.normalize_disparity`` over the view's foreground mask).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from jaxtyping import Float
from torch import Tensor

from depthnerf.data.srn import ObjectViews
from depthnerf.depth.normalize import normalize_disparity
from depthnerf.model.pixelnerf import SourceViews


def source_views(obj: ObjectViews, indices: Sequence[int], disparity: Float[Tensor, "V H W"] | None,
                 device: torch.device | str = "cpu") -> SourceViews:
    """SourceViews (B = 1) from views ``indices`` of ``obj``; ``disparity`` is the raw prior of those views."""
    idx = list(indices)
    prior = None
    if disparity is not None:
        prior = normalize_disparity(disparity, obj.masks[idx])[None, :, None]
    intr = obj.intrinsics
    return SourceViews(images=obj.images[idx][None].to(device), poses=obj.poses[idx][None].to(device),
                       focal=torch.tensor([intr.focal], device=device),
                       principal=torch.tensor([[intr.cx, intr.cy]], device=device),
                       prior=None if prior is None else prior.to(device))
