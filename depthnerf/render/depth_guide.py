"""Depth-guided sampling's guesses (beyond the paper): per-ray depth guesses for a target view from the SOURCE
view's depth prior (settings: :class:`~depthnerf.render.config.GuidedConfig`).

1. Align: the prior is relative disparity; :func:`align_disparity_to_depth` fits ``s p + b ~ 1 / z_ref`` (least
   squares in disparity space) against a metric reference ``z_ref`` on a mask, e.g. the opacity-normalised depth
   of a cheap coarse render of the source view itself, and returns metric z-depth ``1 / (s p + b)``.
2. Guess: :func:`build_depth_guide` marches each target ray (``march_steps`` points between near and far),
   projects the points into the source camera and compares their source z with the aligned source depth at the
   nearest pixel: ``diff = z_map - z_point`` (pixels off the (dilated) mask or off the image: ``+inf``, i.e. the
   source sees empty space there). Then, per ray:

   - *surface crossing* (``valid``): the first point with ``diff <= 0`` and its predecessor are both within
     ``surface_tolerance`` of a foreground pixel's surface; ``t_guess`` is the interpolated zero of ``diff`` and
     the window runs from ``t_enter`` (see below; or ``t_guess - spread`` if earlier) to ``t_guess + spread``, so
     stretches where the ray first passes close to other visible surfaces are covered too.
   - *shadow entry* (``occupied``, not ``valid``): the ray gets within ``spread`` of, or behind, the visible
     surface without crossing it there (a surface hidden from the source, a depth edge, a silhouette); the
     sampler's window runs from ``t_enter``, the first point with ``diff <= spread``, to far.
   - *empty* (not ``occupied``): the source sees the whole ray as free space (``diff > spread`` everywhere).

   Points the source sees in front of its visible surface are empty if the depth is right, hence ``t_enter`` is
   a lower bound on the first surface; the sampler keeps samples over all of [near, far] for every ray, so a
   wrong guess costs accuracy only where those samples are too sparse. Target rays must be in the same world
   frame as the source pose; the source image is assumed to contain the whole object (parts outside it are
   treated as empty).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from jaxtyping import Bool, Float
from torch import Tensor

from depthnerf.bundles import TensorBundle
from depthnerf.data.cameras import Intrinsics, project, world_to_camera
from depthnerf.render.config import GuidedConfig
from depthnerf.render.depth_loss import fit_scale_shift
from depthnerf.render.rays import RayBundle
from depthnerf.render.samplers import stratified_samples


@dataclass
class DepthGuide(TensorBundle):
    """Per-ray depth guesses for ``B x R`` target rays (classes in the module docstring).

    The depth-guided sampler's window is ``[min(t_enter, t_guess - spread), t_guess + spread]`` on ``valid``
    rays, ``[t_enter, far]`` on other ``occupied`` rays; empty rays get no window.
    """

    t_guess: Float[Tensor, "B R"]
    """Guessed ray distance of the first surface where ``valid`` (the crossing of the source-visible surface);
    equal to ``t_enter`` on other occupied rays; 0 on empty rays."""
    t_enter: Float[Tensor, "B R"]
    """First march point within ``spread`` (source z) of, or behind, the source-visible surface: before it the
    source sees empty space; 0 on empty rays."""
    valid: Bool[Tensor, "B R"]
    """The ray crosses the source-visible surface at ``t_guess`` (a trusted guess)."""
    occupied: Bool[Tensor, "B R"]
    """The ray may meet the object (True whenever ``valid``); False: the source view sees it as empty."""
    spread: Float[Tensor, "B R"]
    """Half-width of the window around a trusted ``t_guess`` (ray-distance units)."""

    def window(self, near: Float[Tensor, "B R"], far: Float[Tensor, "B R"]
               ) -> tuple[Float[Tensor, "B R"], Float[Tensor, "B R"]]:
        """The sampling window ``(lo, hi)`` clipped to ``[near, far]`` (meaningless on empty rays)."""
        lo = torch.where(self.valid, torch.minimum(self.t_enter, self.t_guess - self.spread), self.t_enter)
        hi = torch.where(self.valid, self.t_guess + self.spread, far)
        return (torch.minimum(torch.maximum(lo, near), far), torch.minimum(torch.maximum(hi, near), far))


def align_disparity_to_depth(disp: Float[Tensor, "B H W"], ref_depth: Float[Tensor, "B H W"],
                             mask: Bool[Tensor, "B H W"], min_disparity: float = 1e-6) -> Float[Tensor, "B H W"]:
    """Metric z-depth from a relative disparity map by a least-squares scale+shift fit in disparity space.

    Fits ``s, b`` minimising ``sum (s disp + b - 1 / ref_depth)^2`` over ``mask & (ref_depth > 0)`` per image and
    returns ``1 / (s disp + b)``, with 0 (no surface) wherever the aligned disparity is ``<= min_disparity`` or the
    fit had fewer than 2 pixels. Restrict the returned map to the object with your own mask.
    """
    if not (disp.shape == ref_depth.shape == mask.shape):
        raise ValueError(f"align_disparity_to_depth: shapes differ: disp {tuple(disp.shape)}, ref_depth "
                         f"{tuple(ref_depth.shape)}, mask {tuple(mask.shape)}")
    flat_d = disp.reshape(disp.shape[0], -1)
    flat_r = ref_depth.reshape(flat_d.shape)
    fit_mask = mask.reshape(flat_d.shape).bool() & (flat_r > 0) & torch.isfinite(flat_r) & torch.isfinite(flat_d)
    s, b = fit_scale_shift(flat_d, 1.0 / flat_r.clamp_min(1e-12), fit_mask)
    aligned = s[:, None] * flat_d + b[:, None]
    ok = (aligned > min_disparity) & (fit_mask.sum(-1, keepdim=True) >= 2)
    z = torch.where(ok, 1.0 / aligned.clamp_min(min_disparity), torch.zeros_like(aligned))
    return z.reshape(disp.shape)


def _widened_z(depth: Tensor, mask: Tensor, pixels: int) -> Tensor:
    """Foreground z (``inf`` elsewhere) widened by ``pixels``: a background pixel within ``pixels`` of the mask
    (a square window) takes the smallest foreground z among its neighbours. Only the z map widens; the mask itself
    still marks where the surface guess is trusted."""
    z = torch.where(mask, depth, torch.full_like(depth, float("inf")))
    if pixels <= 0:
        return z
    k = 2 * pixels + 1
    z_min = -torch.nn.functional.max_pool2d(-z[:, None], k, stride=1, padding=pixels)[:, 0]
    return torch.where(mask, z, z_min)


def _march_chunk(source_c2w: Tensor, intr: Intrinsics, z_map: Tensor, fg: Tensor, rays: RayBundle,
                 cfg: GuidedConfig) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    bsz, n_rays = rays.near.shape
    k = cfg.march_steps
    t = stratified_samples(rays.near, rays.far, k, random=False)  # [B R K]
    cam = world_to_camera(rays.points(t).reshape(bsz, n_rays * k, 3), source_c2w)  # [B RK 3]
    uv = project(cam, intr.focal, (intr.cx, intr.cy))
    col, row = torch.round(uv[..., 0]), torch.round(uv[..., 1])
    inside = (cam[..., 2] > 0) & (col >= 0) & (col <= intr.width - 1) & (row >= 0) & (row <= intr.height - 1)
    idx = (row.clamp(0, intr.height - 1) * intr.width + col.clamp(0, intr.width - 1)).long()
    z_surf = torch.where(inside, torch.gather(z_map.reshape(bsz, -1), 1, idx), float("inf"))
    on_fg = (inside & torch.gather(fg.reshape(bsz, -1), 1, idx)).reshape(bsz, n_rays, k)
    diff = (z_surf - cam[..., 2]).reshape(bsz, n_rays, k)  # > 0: in front of the visible surface (free)

    def first(cond: Tensor) -> tuple[Tensor, Tensor]:
        return cond.any(-1), cond.to(torch.uint8).argmax(-1)

    def at(x: Tensor, i: Tensor) -> Tensor:
        return torch.gather(x, -1, i[..., None])[..., 0]

    hit, k_hit = first(diff <= 0)
    k_prev = (k_hit - 1).clamp_min(0)
    d_cur, d_prev = at(diff, k_hit), at(diff, k_prev)
    t_cur, t_prev = at(t, k_hit), at(t, k_prev)
    tol = cfg.surface_tolerance
    valid = (hit & (k_hit > 0) & (d_prev <= tol) & (-d_cur <= tol) & at(on_fg, k_hit) & at(on_fg, k_prev))
    frac = torch.where(valid, d_prev / torch.where(valid, d_prev - d_cur, 1.0), 0.0).clamp(0, 1)
    t_hit = t_prev + frac * (t_cur - t_prev)
    occupied, k_near = first(diff <= cfg.spread)
    t_enter = torch.where(occupied, at(t, k_near), 0.0)
    return torch.where(valid, t_hit, t_enter), t_enter, valid, occupied


@torch.no_grad()
def build_depth_guide(source_c2w: Float[Tensor, "B 4 4"], source_intr: Intrinsics,
                      source_depth: Float[Tensor, "B H W"], source_mask: Bool[Tensor, "B H W"], rays: RayBundle,
                      cfg: GuidedConfig) -> DepthGuide:
    """Per-ray depth guesses of target ``rays`` from the source view's aligned z-depth (see module docstring).

    ``source_depth`` is metric z-depth in the source camera (e.g. from :func:`align_disparity_to_depth`), used
    only where ``source_mask`` is True and it is positive; ``source_intr`` must match its ``H x W``.
    """
    if source_depth.shape[-2:] != (source_intr.height, source_intr.width) or source_depth.shape != source_mask.shape:
        raise ValueError(f"build_depth_guide: depth {tuple(source_depth.shape)}, mask {tuple(source_mask.shape)} "
                         f"and intrinsics {source_intr.height}x{source_intr.width} disagree")
    fg = source_mask.bool() & (source_depth > 0) & torch.isfinite(source_depth)
    z_map = _widened_z(source_depth, fg, cfg.mask_dilation)
    outs = [_march_chunk(source_c2w, source_intr, z_map, fg, rays.slice(s, s + cfg.march_chunk), cfg)
            for s in range(0, rays.num_rays, cfg.march_chunk)]
    t_guess, t_enter, valid, occupied = (torch.cat([o[i] for o in outs], dim=1) for i in range(4))
    return DepthGuide(t_guess=t_guess, t_enter=t_enter, valid=valid, occupied=occupied,
                      spread=torch.full_like(t_guess, cfg.spread))
