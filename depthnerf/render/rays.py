"""Ray bundles: world-space rays with near/far bounds, built from cameras in the ``data.cameras`` conventions.

A ray is ``x(t) = o + t d`` with a **unit** world direction ``d``, so ``t`` is ray distance (not z-depth); near and
far bound ``t`` (pixelNeRF's z-near/z-far are ray distances). Pixel (i, j) is centred at ``(u, v) = (j, i)``;
flat pixel index ``k = i * W + j`` (row-major, as ``H W`` images flatten).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from jaxtyping import Float, Int
from torch import Tensor

from depthnerf.bundles import TensorBundle
from depthnerf.data.cameras import Intrinsics, pixel_directions


@dataclass
class RayBundle(TensorBundle):
    """``B`` batches (objects) of ``R`` rays each."""

    origins: Float[Tensor, "B R 3"]
    """World-space ray origins (camera centres)."""
    directions: Float[Tensor, "B R 3"]
    """Unit world-space ray directions."""
    near: Float[Tensor, "B R"]
    """Near bound of the ray distance ``t``."""
    far: Float[Tensor, "B R"]
    """Far bound of the ray distance ``t``."""

    @property
    def num_rays(self) -> int:
        """``R``, the number of rays per batch element."""
        return self.origins.shape[1]

    def points(self, t: Float[Tensor, "B R S"]) -> Float[Tensor, "B R S 3"]:
        """World points ``o + t d`` at ray distances ``t``."""
        return self.origins[..., None, :] + t[..., None] * self.directions[..., None, :]


def _bounds(near: float | Tensor, far: float | Tensor, shape: tuple[int, int], like: Tensor
            ) -> tuple[Tensor, Tensor]:
    """Broadcast scalar / per-batch ``[B]`` / per-ray ``[B R]`` bounds to ``[B R]``."""
    def full(x):
        x = torch.as_tensor(x, dtype=like.dtype, device=like.device)
        return (x[:, None] if x.ndim == 1 else x).expand(shape).contiguous()
    near_t, far_t = full(near), full(far)
    if not bool((far_t > near_t).all()):
        raise ValueError("ray bounds need far > near")
    return near_t, far_t


def rays_from_camera(c2w: Float[Tensor, "B 4 4"], intr: Intrinsics, near: float | Tensor,
                     far: float | Tensor) -> RayBundle:
    """Rays through every pixel centre of each camera, flattened row-major to ``R = H * W``."""
    dirs_cam = pixel_directions(intr).reshape(-1, 3).to(c2w)  # [R 3]
    dirs = dirs_cam @ c2w[:, :3, :3].transpose(-1, -2)  # [B R 3]
    origins = c2w[:, None, :3, 3].expand_as(dirs).contiguous()
    near_t, far_t = _bounds(near, far, dirs.shape[:2], dirs)
    return RayBundle(origins, dirs, near_t, far_t)


def rays_from_pixels(c2w: Float[Tensor, "B 4 4"], intr: Intrinsics, rows: Int[Tensor, "B R"],
                     cols: Int[Tensor, "B R"], near: float | Tensor, far: float | Tensor) -> RayBundle:
    """Rays through pixel centres ``(rows, cols)`` of each camera (for random training rays)."""
    x = (cols.to(c2w.dtype) - intr.cx) / intr.focal
    y = (rows.to(c2w.dtype) - intr.cy) / intr.focal
    dirs_cam = torch.nn.functional.normalize(torch.stack([x, y, torch.ones_like(x)], dim=-1), dim=-1)
    dirs = dirs_cam @ c2w[:, :3, :3].transpose(-1, -2)
    origins = c2w[:, None, :3, 3].expand_as(dirs).contiguous()
    near_t, far_t = _bounds(near, far, dirs.shape[:2], dirs)
    return RayBundle(origins, dirs, near_t, far_t)


def camera_z_of_directions(directions: Float[Tensor, "B R 3"], c2w: Float[Tensor, "B 4 4"]) -> Float[Tensor, "B R"]:
    """Camera-frame z component (``cos theta``) of unit world directions: ``z_depth = t * this``.

    This is the ``dirs_cam_z`` of :func:`depthnerf.data.cameras.ray_distance_to_z`, i.e. ``d . forward`` where
    ``forward`` is the camera's +z axis (third column of the rotation).
    """
    return (directions * c2w[:, None, :3, 2]).sum(-1)
