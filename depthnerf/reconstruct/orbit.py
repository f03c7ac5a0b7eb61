"""Orbit cameras around a reconstructed object and the point cloud of its rendered views.

Conventions of :mod:`depthnerf.data.cameras`: world +z up, object at the origin, camera-to-world poses with
OpenCV axes, ``t`` = distance along unit ray directions. An orbit camera at azimuth ``a`` and elevation ``e``
(degrees) sits at ``radius * (cos e cos a, cos e sin a, sin e)`` and looks at the origin with world +z as up
(:func:`~depthnerf.data.cameras.look_at`). :func:`orbit_poses` starts at the input camera (view 0 reproduces the
input view) and steps the azimuth by ``360 / N`` degrees at constant elevation and radius.

Intrinsics of a reconstruction follow the SRN release: focal ``f`` in pixels of the category's release image size
``S`` (128) with the principal point at ``(S/2, S/2)``, rescaled to the working resolution with
:meth:`Intrinsics.resized` (so ``f * r / S`` and ``(S/2 + 0.5) r / S - 0.5`` at resolution ``r``).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from jaxtyping import Bool, Float
from torch import Tensor

from depthnerf.data.cameras import Intrinsics, backproject, look_at
from depthnerf.errors import DepthnerfError
from depthnerf.render.views import ViewRenders


def orbit_eye(radius: float, elevation_deg: float, azimuth_deg: float) -> Float[Tensor, " 3"]:
    """World position of an orbit camera (see the module docstring)."""
    e, a = math.radians(elevation_deg), math.radians(azimuth_deg)
    return radius * torch.tensor([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])


def orbit_poses(radius: float, elevation_deg: float, views: int, azimuth_deg: float = 0.0
                ) -> Float[Tensor, "N 4 4"]:
    """``views`` camera-to-world poses evenly spaced in azimuth, starting at ``azimuth_deg``."""
    if views < 1:
        raise DepthnerfError(f"--views must be >= 1, got {views}")
    if not radius > 0 or not -89.0 <= elevation_deg <= 89.0:
        raise DepthnerfError(f"camera radius must be > 0 and elevation within [-89, 89] degrees "
                             f"(got {radius}, {elevation_deg})")
    eyes = torch.stack([orbit_eye(radius, elevation_deg, azimuth_deg + 360.0 * k / views) for k in range(views)])
    return look_at(eyes)


def srn_intrinsics(focal: float, image_size: int, resolution: int, pixel_center: float = 0.0) -> Intrinsics:
    """Intrinsics of a square SRN-style camera (focal at ``image_size``, principal point ``image_size / 2`` as
    SRN's files state it) at ``resolution``, read with the pixel-centre convention ``pixel_center`` (the model's
    ``data.pixel_center``) before resizing."""
    if not focal > 0 or resolution < 1:
        raise DepthnerfError(f"focal must be > 0 and resolution >= 1 (got {focal}, {resolution})")
    base = Intrinsics(focal=focal, cx=image_size / 2, cy=image_size / 2, height=image_size, width=image_size)
    return base.with_pixel_center(pixel_center).resized(resolution, resolution)


def unproject(poses: Float[Tensor, "N 4 4"], intr: Intrinsics, distance: Float[Tensor, "N H W"],
              keep: Bool[Tensor, "N H W"]) -> Float[np.ndarray, "P 3"]:
    """World points ``o + t d`` of the kept pixels of N views, ``t`` = ``distance``, the ray distance along unit
    directions."""
    out = [backproject(t, pose, intr, k, ray_distance=True).numpy() for pose, t, k in zip(poses, distance, keep,
                                                                                           strict=True)]
    return np.concatenate(out) if out else np.zeros((0, 3), dtype=np.float32)


def orbit_points(renders: ViewRenders, poses: Float[Tensor, "N 4 4"], intr: Intrinsics, min_opacity: float,
                 max_points: int | None) -> tuple[Float[np.ndarray, "P 3"], Float[np.ndarray, "P 3"]]:
    """Point cloud of rendered views: ray distance unprojected where opacity > ``min_opacity``, with the rendered
    colours; an even subsample of at most ``max_points`` points (None: all)."""
    keep = renders.opacity > min_opacity
    points = unproject(poses, intr, renders.distance, keep)
    colors = renders.rgb[keep].numpy()
    if max_points is not None and len(points) > max_points:
        idx = np.linspace(0, len(points) - 1, max_points).round().astype(np.int64)
        points, colors = points[idx], colors[idx]
    return points, colors
