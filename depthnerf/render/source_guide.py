"""Depth-guided sampling as an inference path: source prior -> aligned source depth -> per-ray guide -> renderer.

1. :func:`source_depth`: the source view's relative disparity is aligned to metric z-depth against a cheap
   coarse-only render of the source view (``GuidedConfig.align_samples`` samples per ray) on mask pixels whose
   render opacity exceeds ``align_min_opacity`` (:func:`~depthnerf.render.depth_guide.align_disparity_to_depth`);
   without a prior, that render's own depth on those pixels.
2. :class:`SourceGuide`: that depth with the source camera and mask; ``guide(rays)`` builds the per-ray
   :class:`~depthnerf.render.depth_guide.DepthGuide` of any target rays
   (:func:`~depthnerf.render.depth_guide.build_depth_guide`).
3. The renderer: the checkpoint's render config with ``guided`` set to the request (:func:`guided_config` splits
   one ``--guided BUDGET`` into the sampler's counts); :func:`~depthnerf.render.views.render_poses` takes the
   :class:`SourceGuide`.

Every setting of the three steps is one :class:`~depthnerf.render.config.GuidedConfig`. ``depthnerf eval
--guided``, ``depthnerf reconstruct --guided``, :class:`~depthnerf.reconstruct.Reconstructor`
(``ReconstructConfig.guided``), all through :class:`~depthnerf.infer.InferenceSession`, and
``benchmarks/bench_guided_sampling.py`` use this module.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import torch
from jaxtyping import Bool, Float
from torch import Tensor

from depthnerf.data.cameras import Intrinsics
from depthnerf.errors import DepthnerfError
from depthnerf.render.config import DEFAULT_BUDGET, GuidedConfig, RenderConfig, SamplerConfig
from depthnerf.render.depth_guide import DepthGuide, align_disparity_to_depth, build_depth_guide
from depthnerf.render.pipeline import FieldFn, render_image
from depthnerf.render.rays import RayBundle, camera_z_of_directions, rays_from_camera

__all__ = ["DEFAULT_BUDGET", "MIN_BUDGET", "SourceGuide", "as_guided", "guided_config", "guided_record",
           "make_source_guide", "source_depth"]

MIN_BUDGET = 6
"""Fewest samples per occupied ray a guided budget may have (one per occupied-ray count, and more)."""


def _split(total: int, weights: tuple[int, ...]) -> list[int]:
    """``total`` split in proportion to ``weights`` (largest remainder; ties to the earlier entry)."""
    shares = [total * w / sum(weights) for w in weights]
    parts = [int(s) for s in shares]
    order = sorted(range(len(shares)), key=lambda k: (parts[k] - shares[k], k))
    for k in order[: total - sum(parts)]:
        parts[k] += 1
    return parts


def guided_config(budget: int = DEFAULT_BUDGET, align_samples: int = GuidedConfig.align_samples,
                  base: GuidedConfig | None = None) -> GuidedConfig:
    """Depth-guided sampling switched on at ``budget`` samples per occupied ray, split 1:2:2:1 (uniform, window,
    importance, Gaussian: the default 8:16:16:8's proportions), and ``budget // 2`` per empty ray split 2:1 (the
    default 16:8's); ``align_samples`` for the alignment render; every other setting ``base``'s (default:
    :class:`GuidedConfig`'s)."""
    if budget < MIN_BUDGET:
        raise DepthnerfError(f"--guided {budget}: a guided budget needs >= {MIN_BUDGET} samples per ray")
    if align_samples < 1:
        raise DepthnerfError(f"--guided-align-samples must be >= 1, got {align_samples}")
    n_uniform, n_window, n_importance, n_gaussian = _split(budget, (1, 2, 2, 1))
    n_empty, n_empty_importance = _split(budget // 2, (2, 1))
    return dataclasses.replace(base or GuidedConfig(), enabled=True, n_uniform=n_uniform, n_window=n_window,
                               n_importance=n_importance, n_gaussian=n_gaussian, n_empty=n_empty,
                               n_empty_importance=n_empty_importance, align_samples=align_samples)


def as_guided(value: GuidedConfig | int | bool | None, where: str = "guided") -> GuidedConfig | None:
    """A guided request as the Python API takes it: a :class:`GuidedConfig` as it is, a budget (``guided=48``, the
    CLI's ``--guided 48``) through :func:`guided_config`, ``True`` at the default budget, ``None`` / ``False`` for
    none; anything else is a one-line error naming ``where``."""
    if value is None or value is False:
        return None
    if value is True:
        return guided_config()
    if isinstance(value, GuidedConfig):
        return value
    if isinstance(value, int):
        return guided_config(value)
    raise DepthnerfError(f"{where}={value!r}: give a budget (samples per occupied ray, e.g. {DEFAULT_BUDGET}), True "
                         f"for the default budget, a GuidedConfig, or None")


def guided_record(guided: GuidedConfig) -> dict[str, Any]:
    """What an evaluation summary records of a guided request (``guided_sampling``: the budget, the alignment
    and the guesses' settings)."""
    return {"budget": guided.budget, "align_samples": guided.align_samples,
            "align_min_opacity": guided.align_min_opacity,
            "guide": {"march_steps": guided.march_steps, "spread": guided.spread,
                      "surface_tolerance": guided.surface_tolerance, "mask_dilation": guided.mask_dilation,
                      "chunk": guided.march_chunk}}


@torch.no_grad()
def source_depth(coarse: FieldFn, c2w: Float[Tensor, "1 4 4"], intr: Intrinsics, near: float, far: float,
                 disparity: Float[Tensor, "1 H W"] | None, mask: Bool[Tensor, "1 H W"], render: RenderConfig,
                 guided: GuidedConfig, chunk: int = 4096) -> Float[Tensor, "1 H W"]:
    """Metric z-depth of the source view for the guide (step 1 of the module docstring)."""
    rays = rays_from_camera(c2w, intr, near, far)
    cfg = dataclasses.replace(render, sampler=SamplerConfig(n_coarse=guided.align_samples),
                              guided=dataclasses.replace(render.guided, enabled=False))
    cheap = render_image(coarse, None, rays, cfg, chunk=chunk).coarse
    shape = mask.shape
    ref_z = (cheap.normalized_distance() * camera_z_of_directions(rays.directions, c2w)).reshape(shape)
    opacity = cheap.opacity.reshape(shape)
    anchors = mask & (opacity > guided.align_min_opacity)
    if disparity is None:
        return torch.where(anchors, ref_z, torch.zeros_like(ref_z))
    return align_disparity_to_depth(disparity, ref_z, anchors)


@dataclass
class SourceGuide:
    """The source view's aligned depth, from which any target rays get their :class:`DepthGuide`."""

    c2w: Float[Tensor, "1 4 4"]
    """Source camera-to-world pose."""
    intr: Intrinsics
    """Source intrinsics (matching ``depth``)."""
    depth: Float[Tensor, "1 H W"]
    """Metric z-depth of the source view (0: no surface)."""
    mask: Bool[Tensor, "1 H W"]
    """Source foreground mask."""
    guided: GuidedConfig
    """How guesses are made."""

    def guide(self, rays: RayBundle) -> DepthGuide:
        """Per-ray guesses for target ``rays`` (same world frame as the source pose)."""
        return build_depth_guide(self.c2w, self.intr, self.depth, self.mask, rays, self.guided)


def make_source_guide(coarse: FieldFn, c2w: Float[Tensor, "1 4 4"], intr: Intrinsics, near: float, far: float,
                      disparity: Float[Tensor, "1 H W"] | None, mask: Bool[Tensor, "1 H W"], render: RenderConfig,
                      guided: GuidedConfig, chunk: int = 4096) -> SourceGuide:
    """Steps 1-2 of the module docstring for one encoded object's source view (``render``: the checkpoint's
    renderer, whose sampler the alignment render replaces)."""
    depth = source_depth(coarse, c2w, intr, near, far, disparity, mask, render, guided, chunk)
    return SourceGuide(c2w=c2w, intr=intr, depth=depth, mask=mask, guided=guided)
