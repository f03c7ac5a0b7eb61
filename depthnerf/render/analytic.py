"""Analytic scenes with closed-form geometry, for tests and benchmarks of the renderer (no network needed).

:class:`SphereScene` is a :data:`~depthnerf.render.pipeline.FieldFn`: a union of spheres turned into density by the
VolSDF transform ``sigma = Psi_beta(-sdf) / beta`` (``Psi_beta`` the Laplace CDF with scale ``beta``: density
``1 / (2 beta)`` on the surface, ``-> 1 / beta`` inside, ``-> 0`` outside), coloured by a smooth position pattern so
images have structure. Its exact first ray-surface intersections give ground-truth depth.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from jaxtyping import Bool, Float
from torch import Tensor

from depthnerf.data.cameras import Intrinsics
from depthnerf.render.rays import RayBundle, camera_z_of_directions, rays_from_camera


@dataclass(frozen=True)
class Sphere:
    """One sphere."""

    center: tuple[float, float, float]
    """World-space centre."""
    radius: float
    """Radius."""


@dataclass(frozen=True)
class SphereScene:
    """Union of spheres as a density field (callable as a FieldFn)."""

    spheres: tuple[Sphere, ...]
    """The spheres."""
    beta: float = 0.005
    """Laplace scale of the SDF-to-density transform: smaller = sharper surface, max density ``1 / beta``."""
    pattern_frequency: float = 12.0
    """Spatial frequency of the colour pattern ``0.5 + 0.4 sin(f x + phase_c)`` per channel."""

    def sdf(self, points: Float[Tensor, "*N 3"]) -> Float[Tensor, "*N"]:
        """Signed distance to the union (negative inside)."""
        centers = torch.tensor([s.center for s in self.spheres], dtype=points.dtype, device=points.device)
        radii = torch.tensor([s.radius for s in self.spheres], dtype=points.dtype, device=points.device)
        dist = (points[..., None, :] - centers).norm(dim=-1) - radii
        return dist.min(-1).values

    def __call__(self, points: Float[Tensor, "B R S 3"], dirs: Float[Tensor, "B R 3"]
                 ) -> tuple[Float[Tensor, "B R S 3"], Float[Tensor, "B R S"]]:
        s = -self.sdf(points) / self.beta
        psi = torch.where(s <= 0, 0.5 * torch.exp(s.clamp_max(0)), 1 - 0.5 * torch.exp(-s.clamp_min(0)))
        phase = torch.tensor([0.0, 2.1, 4.2], dtype=points.dtype, device=points.device)
        rgb = 0.5 + 0.4 * torch.sin(self.pattern_frequency * points.sum(-1, keepdim=True) + phase)
        return rgb, psi / self.beta

    def ray_hits(self, rays: RayBundle) -> tuple[Float[Tensor, "B R"], Bool[Tensor, "B R"]]:
        """Exact ray distance of the first surface hit in ``[near, far]`` and whether there is one."""
        best = torch.full_like(rays.near, float("inf"))
        for sph in self.spheres:
            oc = rays.origins - torch.tensor(sph.center, dtype=rays.origins.dtype, device=rays.origins.device)
            bq = (oc * rays.directions).sum(-1)
            disc = bq * bq - ((oc * oc).sum(-1) - sph.radius ** 2)
            root = -bq - disc.clamp_min(0).sqrt()
            ok = (disc >= 0) & (root >= rays.near) & (root <= rays.far)
            best = torch.where(ok, torch.minimum(best, root), best)
        hit = torch.isfinite(best)
        return torch.where(hit, best, torch.zeros_like(best)), hit

    def depth_map(self, c2w: Float[Tensor, "B 4 4"], intr: Intrinsics, near: float, far: float
                  ) -> tuple[Float[Tensor, "B H W"], Bool[Tensor, "B H W"]]:
        """Exact z-depth image (0 off the object) and object mask of each camera."""
        rays = rays_from_camera(c2w, intr, near, far)
        t, hit = self.ray_hits(rays)
        z = t * camera_z_of_directions(rays.directions, c2w)
        shape = (c2w.shape[0], intr.height, intr.width)
        return z.reshape(shape), hit.reshape(shape)
