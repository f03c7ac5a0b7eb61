"""Camera conventions of depthnerf, stated once and followed everywhere.

World frame
    Right-handed, +z is world up, objects centred at the origin. (SRN's own pose files have +y up, ShapeNetCore
    v2's up axis; nothing in the model depends on the world's up axis, and ``depthnerf synth`` maps SRN's framing
    into this frame: docs/data.md.)
    Cameras look at the origin from a sphere of radius ~1.3 (cars) or ~2.0 (chairs), on the upper hemisphere.

Camera frame (OpenCV axes, as stored in SRN ``pose/*.txt``)
    +x right, +y down, +z forward (into the scene). A pose is a 4x4 **camera-to-world** matrix ``c2w`` with
    ``x_world = R @ x_cam + t``. depthnerf keeps OpenCV axes in memory too (pixelNeRF flips to OpenGL axes with
    ``diag(1, -1, -1, 1)``; that is a sign change of the camera-frame coordinates that the positional encoding and
    the first linear layer absorb, so the learned function class is the same).

Pixels
    Pixel (row i, column j) has its centre at image coordinates ``(u, v) = (j, i)`` (integer-centred, as pixelNeRF
    generates rays), so ``u = f * x / z + cx`` and ``v = f * y / z + cy``. Intrinsics are one focal length ``f``
    (square pixels) and the principal point ``(cx, cy)``.
    Resizing by a factor ``s`` (new/old) maps ``f -> f * s`` and ``c -> (c + 0.5) * s - 0.5`` (exact for
    integer-centred pixels and area resampling).
    Datasets state their own convention: Blender renders (SRN, ``depthnerf synth --framing srn``) put pixel
    (i, j) at ``(j + 0.5, i + 0.5)`` in the coordinates of their ``intrinsics.txt``. A pixel-centre offset ``c`` is
    exactly a principal-point shift ``(cx, cy) -> (cx - c, cy - c)`` in the integer-centred convention
    (:meth:`Intrinsics.with_pixel_center`), applied once where a dataset's intrinsics are read, at the file's
    resolution and before any resize; ray generation and feature projection then both use the shifted
    intrinsics and stay consistent. The offset is the training config's ``data.pixel_center`` (default 0.0,
    pixelNeRF's reading, half a pixel off SRN's renders; 0.5 reads them as rendered), stored in every run and
    checkpoint; eval, reconstruct and the demo use the trained value.

Depth
    *z-depth* is the camera-frame ``z`` of a surface point (what ``depth/`` folders and depth priors store).
    *Ray distance* ``t`` is the distance along a **unit** ray direction (what the renderer samples, and what
    z-near/z-far bound, as in pixelNeRF). ``z = t * cos(theta)`` with ``cos(theta) = d_cam[2]`` for the unit
    direction ``d_cam`` in the camera frame: see :func:`ray_distance_to_z`.
    *Disparity* is ``1 / z`` (larger = closer); monocular priors are relative disparity, defined up to scale
    and shift.

SRN z-ranges (ray distance, from pixelNeRF): cars 0.8-1.8, chairs 1.25-2.75.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from jaxtyping import Bool, Float
from torch import Tensor


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics with square pixels, in the integer-centred pixel convention above."""

    focal: float
    """Focal length in pixels."""
    cx: float
    """Principal point, column coordinate (pixels)."""
    cy: float
    """Principal point, row coordinate (pixels)."""
    height: int
    """Image height in pixels."""
    width: int
    """Image width in pixels."""

    def resized(self, height: int, width: int) -> Intrinsics:
        """Intrinsics of the same camera after resampling the image to ``height x width``."""
        sy, sx = height / self.height, width / self.width
        if not math.isclose(sx, sy, rel_tol=1e-6):
            raise ValueError(f"non-uniform resize {self.height}x{self.width} -> {height}x{width}")
        return Intrinsics(
            focal=self.focal * sx,
            cx=(self.cx + 0.5) * sx - 0.5,
            cy=(self.cy + 0.5) * sy - 0.5,
            height=height,
            width=width,
        )

    def with_pixel_center(self, center: float) -> Intrinsics:
        """The integer-centred intrinsics of an image whose pixel (row i, column j) has its centre at
        ``(j + center, i + center)`` in these intrinsics' image coordinates: ``(cx, cy) -> (cx - c, cy - c)``
        (``center`` 0.5: Blender/SRN renders; 0: pixelNeRF's reading). Apply before :meth:`resized`."""
        if center == 0.0:
            return self
        return Intrinsics(focal=self.focal, cx=self.cx - center, cy=self.cy - center, height=self.height,
                          width=self.width)

    def matrix(self) -> Float[Tensor, "3 3"]:
        """The 3x3 matrix ``K`` with ``[u, v, 1]^T ~ K @ x_cam``."""
        return torch.tensor(
            [[self.focal, 0.0, self.cx], [0.0, self.focal, self.cy], [0.0, 0.0, 1.0]], dtype=torch.float32
        )


def look_at(eye: Float[Tensor, "*B 3"], target: Float[Tensor, "*B 3"] | None = None,
            up: Float[Tensor, " 3"] | None = None) -> Float[Tensor, "*B 4 4"]:
    """Camera-to-world poses (OpenCV axes) of cameras at ``eye`` looking at ``target`` (default: origin).

    ``up`` (default world +z) fixes the roll: the camera's -y axis (image up) is as close to ``up`` as possible.
    Undefined when the viewing direction is parallel to ``up``.
    """
    eye = torch.as_tensor(eye, dtype=torch.float32)
    target = torch.zeros_like(eye) if target is None else torch.as_tensor(target, dtype=eye.dtype).expand_as(eye)
    up = torch.tensor([0.0, 0.0, 1.0]) if up is None else torch.as_tensor(up, dtype=eye.dtype)
    forward = torch.nn.functional.normalize(target - eye, dim=-1)  # camera +z
    right = torch.nn.functional.normalize(torch.linalg.cross(forward, up.expand_as(forward)), dim=-1)  # +x
    down = torch.linalg.cross(forward, right)  # +y = z cross x
    c2w = torch.zeros(*eye.shape[:-1], 4, 4, dtype=eye.dtype)
    c2w[..., :3, 0], c2w[..., :3, 1], c2w[..., :3, 2], c2w[..., :3, 3] = right, down, forward, eye
    c2w[..., 3, 3] = 1.0
    return c2w


def invert_pose(c2w: Float[Tensor, "*B 4 4"]) -> Float[Tensor, "*B 4 4"]:
    """World-to-camera from camera-to-world for a rigid transform (``R^T``, ``-R^T t``)."""
    rot, trans = c2w[..., :3, :3], c2w[..., :3, 3:]
    out = torch.zeros_like(c2w)
    out[..., :3, :3] = rot.transpose(-1, -2)
    out[..., :3, 3:] = -rot.transpose(-1, -2) @ trans
    out[..., 3, 3] = 1.0
    return out


def world_to_camera(points: Float[Tensor, "*B N 3"], c2w: Float[Tensor, "*B 4 4"]) -> Float[Tensor, "*B N 3"]:
    """Express world points in the camera frame of ``c2w``: ``R^T (x - t)``."""
    rot, trans = c2w[..., :3, :3], c2w[..., None, :3, 3]
    return (points - trans) @ rot


def project(points_cam: Float[Tensor, "*B N 3"], focal: Float[Tensor, "*B"] | float,
            principal: Float[Tensor, "*B 2"] | tuple[float, float]) -> Float[Tensor, "*B N 2"]:
    """Pixel coordinates ``(u, v)`` of camera-frame points: ``u = f x / z + cx``, ``v = f y / z + cy``.

    Points behind the camera (``z <= 0``) get coordinates far outside the image rather than NaN. A Python number
    or tuple becomes a tensor of the points' dtype; a tensor is used as it is (torch's type promotion, so the
    model's features, :func:`depthnerf.model.features.project_points`, keep their dtype behaviour).
    """
    if not isinstance(focal, Tensor):
        focal = torch.as_tensor(focal, dtype=points_cam.dtype, device=points_cam.device)
    if not isinstance(principal, Tensor):
        principal = torch.as_tensor(principal, dtype=points_cam.dtype, device=points_cam.device)
    z = points_cam[..., 2:3].clamp_min(1e-6)
    return points_cam[..., :2] / z * focal[..., None, None] + principal[..., None, :]


def pixel_directions(intr: Intrinsics, *, normalize: bool = True) -> Float[Tensor, "H W 3"]:
    """Camera-frame ray directions through every pixel centre (unit length unless ``normalize=False``,
    in which case ``z == 1``)."""
    v, u = torch.meshgrid(torch.arange(intr.height, dtype=torch.float32),
                          torch.arange(intr.width, dtype=torch.float32), indexing="ij")
    dirs = torch.stack([(u - intr.cx) / intr.focal, (v - intr.cy) / intr.focal, torch.ones_like(u)], dim=-1)
    return torch.nn.functional.normalize(dirs, dim=-1) if normalize else dirs


def camera_rays(c2w: Float[Tensor, "4 4"], intr: Intrinsics) -> tuple[Float[Tensor, "H W 3"], Float[Tensor, "H W 3"]]:
    """World-space ray origins and unit directions for every pixel of one camera."""
    dirs = pixel_directions(intr) @ c2w[:3, :3].T
    origins = c2w[:3, 3].expand_as(dirs)
    return origins, dirs


def backproject(depth: Float[Tensor, "H W"], c2w: Float[Tensor, "4 4"], intr: Intrinsics,
                keep: Bool[Tensor, "H W"], *, ray_distance: bool = False) -> Float[Tensor, "P 3"]:
    """World points of the ``keep`` pixels of a depth map seen from camera ``c2w``, in ``depth``'s dtype.

    ``depth`` is z-depth (``ray_distance=False``: camera point = ``z * (x/z, y/z, 1)``) or the distance along unit
    ray directions (``ray_distance=True``: camera point = ``t * d / |d|``, the renderer's ``t``).
    """
    dirs = pixel_directions(intr, normalize=ray_distance).to(depth.dtype)
    cam = dirs[keep] * depth[keep][:, None]
    c2w = c2w.to(depth.dtype)
    return cam @ c2w[:3, :3].T + c2w[:3, 3]


def ray_distance_to_z(t: Tensor, dirs_cam_z: Tensor) -> Tensor:
    """z-depth from ray distance along a unit direction whose camera-frame z component is ``dirs_cam_z``."""
    return t * dirs_cam_z
