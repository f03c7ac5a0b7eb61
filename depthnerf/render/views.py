"""Rendering whole images of one encoded object from a set of target cameras (validation, eval, reconstruction).

The field callables close over ONE object (batch size 1); all target views' rays are concatenated into one
``[1, N*H*W]`` bundle and rendered in chunks by :func:`~depthnerf.render.pipeline.render_image`, so memory is
bounded by ``chunk`` whatever N and the image size are.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from jaxtyping import Float
from torch import Tensor

from depthnerf.bundles import TensorBundle
from depthnerf.data.cameras import Intrinsics
from depthnerf.errors import DepthnerfError
from depthnerf.model.pixelnerf import EncodedViews, FieldRuntime, PixelNeRF
from depthnerf.render.config import RenderConfig
from depthnerf.render.depth_guide import DepthGuide
from depthnerf.render.pipeline import FieldFn, render_image
from depthnerf.render.rays import RayBundle, rays_from_camera
from depthnerf.render.source_guide import SourceGuide


@dataclass
class ViewRenders(TensorBundle):
    """Rendered images of N target views (the fine pass when there is one)."""

    rgb: Float[Tensor, "N H W 3"]
    """Colour in [0, 1] on the configured background."""
    distance: Float[Tensor, "N H W"]
    """Expected ray distance divided by opacity (the visible surface's distance along the unit ray, not z-depth;
    ``far`` where opacity ~ 0)."""
    opacity: Float[Tensor, "N H W"]
    """Accumulated opacity in [0, 1]."""


def view_rays(c2w: Float[Tensor, "N 4 4"], intr: Intrinsics, near: float, far: float) -> RayBundle:
    """All pixels of N cameras as one ``[1, N*H*W]`` bundle (view-major, then row-major pixels)."""
    rays = rays_from_camera(c2w, intr, near, far)  # [N, H*W]
    return rays.map(lambda x: x.reshape(1, -1, *x.shape[2:]))


@torch.no_grad()
def render_views(coarse: FieldFn, fine: FieldFn | None, c2w: Float[Tensor, "N 4 4"], intr: Intrinsics,
                 near: float, far: float, cfg: RenderConfig, *, chunk: int = 4096,
                 guide: DepthGuide | None = None) -> ViewRenders:
    """Render N full views of one encoded object (deterministic sampling, no gradients)."""
    n, h, w = c2w.shape[0], intr.height, intr.width
    rays = view_rays(c2w, intr, near, far)
    out = render_image(coarse, fine, rays, cfg, chunk=chunk, guide=guide)
    res = out.fine if out.fine is not None else out.coarse
    opacity = res.opacity.reshape(n, h, w)
    distance = torch.where(opacity > 1e-4, res.distance.reshape(n, h, w) / opacity.clamp_min(1e-4),
                           torch.full_like(opacity, far))
    return ViewRenders(rgb=res.rgb.reshape(n, h, w, 3).clamp(0, 1), distance=distance, opacity=opacity)


@torch.no_grad()
def render_poses(model: PixelNeRF, enc: EncodedViews, poses: Float[Tensor, "N 4 4"], intr: Intrinsics, near: float,
                 far: float, cfg: RenderConfig, chunk: int, device: torch.device | str,
                 on_group: Callable[[int], None] | None = None, guide: SourceGuide | None = None,
                 runtime: FieldRuntime | None = None) -> ViewRenders:
    """Render N views of one encoded object (CPU float tensors), ``max(1, chunk // (H*W))`` views per call and
    ``chunk`` rays per pass, so memory stays bounded; ``on_group(n)`` runs after each group of ``n`` views;
    the fields run as ``runtime`` says (``depthnerf.render.precision.field_runtime``; None: the default).

    With ``cfg.guided.enabled`` (depth-guided sampling, :mod:`depthnerf.render.source_guide`) ``guide`` gives every
    target ray its depth guess from the source view; a guided config without a guide is an error.
    """
    if cfg.guided.enabled and guide is None:
        raise DepthnerfError("render.guided (depth-guided sampling) needs the source view's guide: use --guided "
                             "with depthnerf eval/reconstruct rather than a guided render config")
    if chunk < 1:
        raise DepthnerfError(f"--chunk must be >= 1, got {chunk}")
    coarse, fine = model.field(enc, "coarse", runtime), model.field(enc, "fine", runtime)
    group = max(1, chunk // (intr.height * intr.width))
    parts = []
    for start in range(0, len(poses), group):
        c2w = poses[start:start + group].to(device)
        ray_guide = guide.guide(view_rays(c2w, intr, near, far)) if cfg.guided.enabled else None
        res = render_views(coarse, fine, c2w, intr, near, far, cfg, chunk=chunk, guide=ray_guide)
        parts.append(res.map(lambda x: x.float().cpu()))
        if on_group is not None:
            on_group(len(res.rgb))
    return ViewRenders.cat(parts)
