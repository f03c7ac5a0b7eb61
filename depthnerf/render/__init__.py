"""Render stage: ray samplers and volume rendering as pure functions; the network is passed in.

Public API: :class:`RayBundle` and ray builders (``rays``), samplers (``samplers``), compositing (``volume``),
:func:`render_rays` / :func:`render_image` (``pipeline``), depth-guided sampling (``depth_guide``,
``guided_sampler``, ``source_guide``), the SSI depth loss (``depth_loss``), configs (``config``) and analytic test
scenes (``analytic``).
"""

from depthnerf.render.config import GuidedConfig, RenderConfig, SamplerConfig
from depthnerf.render.depth_guide import DepthGuide, align_disparity_to_depth, build_depth_guide
from depthnerf.render.depth_loss import fit_scale_shift, ssi_depth_loss
from depthnerf.render.pipeline import FieldFn, RenderOutput, render_image, render_rays
from depthnerf.render.rays import RayBundle, camera_z_of_directions, rays_from_camera, rays_from_pixels
from depthnerf.render.volume import RenderResult, composite

__all__ = [
    "DepthGuide", "FieldFn", "GuidedConfig", "RayBundle", "RenderConfig", "RenderOutput",
    "RenderResult", "SamplerConfig", "align_disparity_to_depth", "build_depth_guide", "camera_z_of_directions",
    "composite", "fit_scale_shift", "rays_from_camera", "rays_from_pixels", "render_image", "render_rays",
    "ssi_depth_loss",
]
