"""Depth-guided sampling as an inference path: source prior -> aligned source depth -> per-ray guide -> renderer.

1. :func:`source_depth`: the source view's relative-disparity prior is aligned to metric z-depth against a cheap
   coarse-only render of the source view (``align_samples`` samples per ray) on mask pixels whose render opacity
   exceeds ``align_min_opacity`` (:func:`~depthnerf.render.guide.align_disparity_to_depth`); without a prior, that
   render's own depth on those pixels.
2. :class:`SourceGuide`: that depth with the source camera and mask; ``guide(rays)`` builds the per-ray
   :class:`~depthnerf.render.guide.DepthGuide` of any target rays (:func:`~depthnerf.render.guide.build_depth_guide`).
3. :func:`guided_render`: the checkpoint's renderer with the depth-guided sampler at a per-ray ``budget``
   (:func:`guided_sampler`); :func:`~depthnerf.render.views.render_poses` takes the :class:`SourceGuide`.

``depthnerf eval --guided``, ``depthnerf reconstruct --guided``, :class:`~depthnerf.reconstruct.Reconstructor`
(``ReconstructConfig.guided``) and ``benchmarks/bench_guided_sampling.py`` all use this module.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import torch
from jaxtyping import Bool, Float
from torch import Tensor

from depthnerf.data.cameras import Intrinsics
from depthnerf.errors import DepthnerfError
from depthnerf.render.config import GuideConfig, GuidedSamplerConfig, RenderConfig, SamplerConfig
from depthnerf.render.guide import DepthGuide, align_disparity_to_depth, build_depth_guide
from depthnerf.render.pipeline import FieldFn, render_image
from depthnerf.render.rays import RayBundle, camera_z_of_directions, rays_from_camera

ALIGN_MIN_OPACITY = 0.5
"""Source pixels whose cheap coarse render is at least this opaque anchor the prior's scale/shift fit. Soft
CPU models rarely exceed 0.9 (a threshold of 0.9 left the guide empty on most objects)."""


DEFAULT_BUDGET = 48
"""Samples per occupied ray of ``--guided`` without a number: the smallest budget measured to cost at most 0.1 dB of
PSNR against the shipped CPU checkpoints' own sampler (cars -0.08, chairs -0.04 dB; docs/RESULTS.md)."""


@dataclass(frozen=True)
class GuidanceConfig:
    """Depth-guided sampling at inference (``--guided BUDGET``)."""

    budget: int = DEFAULT_BUDGET
    """Samples per occupied ray (split 1:2:2:1 into uniform, window, importance, Gaussian; empty rays get half)."""
    align_samples: int = 32
    """Coarse samples per ray of the source render the prior is aligned against."""
    align_min_opacity: float = ALIGN_MIN_OPACITY
    """Source pixels at least this opaque in that render anchor the alignment."""
    guide: GuideConfig = field(default_factory=GuideConfig)
    """How per-ray guesses are made."""


def _split(total: int, weights: tuple[int, ...]) -> list[int]:
    """``total`` split in proportion to ``weights`` (largest remainder; ties to the earlier entry)."""
    shares = [total * w / sum(weights) for w in weights]
    parts = [int(s) for s in shares]
    order = sorted(range(len(shares)), key=lambda k: (parts[k] - shares[k], k))
    for k in order[: total - sum(parts)]:
        parts[k] += 1
    return parts


def guided_sampler(total: int, base: GuidedSamplerConfig) -> GuidedSamplerConfig:
    """``base`` with ``total`` samples per occupied ray split 1:2:2:1 (uniform, window, importance, Gaussian, the
    default 8:16:16:8's proportions) and ``total // 2`` per empty ray split 2:1 (the default 16:8's)."""
    if total < 6:
        raise DepthnerfError(f"a guided sampling budget needs >= 6 samples per ray, got {total}")
    n_uniform, n_window, n_importance, n_gaussian = _split(total, (1, 2, 2, 1))
    n_empty, n_empty_importance = _split(total // 2, (2, 1))
    return dataclasses.replace(base, enabled=True, n_uniform=n_uniform, n_window=n_window,
                               n_importance=n_importance, n_gaussian=n_gaussian, n_empty=n_empty,
                               n_empty_importance=n_empty_importance)


def guided_render(render: RenderConfig, budget: int) -> RenderConfig:
    """``render`` with the depth-guided sampler at ``budget`` samples per occupied ray."""
    return dataclasses.replace(render, guided=guided_sampler(budget, render.guided))


@torch.no_grad()
def source_depth(coarse: FieldFn, c2w: Float[Tensor, "1 4 4"], intr: Intrinsics, near: float, far: float,
                 prior: Float[Tensor, "1 H W"] | None, mask: Bool[Tensor, "1 H W"], samples: int,
                 render: RenderConfig, chunk: int = 4096, min_opacity: float = ALIGN_MIN_OPACITY
                 ) -> Float[Tensor, "1 H W"]:
    """Metric z-depth of the source view for the guide (step 1 of the module docstring)."""
    rays = rays_from_camera(c2w, intr, near, far)
    cfg = dataclasses.replace(render, sampler=SamplerConfig(n_coarse=samples),
                              guided=GuidedSamplerConfig(enabled=False))
    cheap = render_image(coarse, None, rays, cfg, chunk=chunk).coarse
    shape = mask.shape
    ref_z = (cheap.normalized_depth() * camera_z_of_directions(rays.directions, c2w)).reshape(shape)
    opacity = cheap.opacity.reshape(shape)
    if prior is None:
        return torch.where(mask & (opacity > min_opacity), ref_z, torch.zeros_like(ref_z))
    return align_disparity_to_depth(prior, ref_z, mask & (opacity > min_opacity))


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
    cfg: GuideConfig
    """How guesses are made."""

    def guide(self, rays: RayBundle) -> DepthGuide:
        """Per-ray guesses for target ``rays`` (same world frame as the source pose)."""
        return build_depth_guide(self.c2w, self.intr, self.depth, self.mask, rays, self.cfg)


def make_source_guide(coarse: FieldFn, c2w: Float[Tensor, "1 4 4"], intr: Intrinsics, near: float, far: float,
                      prior: Float[Tensor, "1 H W"] | None, mask: Bool[Tensor, "1 H W"], render: RenderConfig,
                      cfg: GuidanceConfig, chunk: int = 4096) -> SourceGuide:
    """Steps 1-2 of the module docstring for one encoded object's source view."""
    depth = source_depth(coarse, c2w, intr, near, far, prior, mask, cfg.align_samples, render, chunk,
                         cfg.align_min_opacity)
    return SourceGuide(c2w=c2w, intr=intr, depth=depth, mask=mask, cfg=cfg.guide)
