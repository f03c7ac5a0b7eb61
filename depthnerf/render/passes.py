"""Building blocks shared by the samplers' orchestrations: the FieldFn contract, field evaluation, output bundles.

A pass evaluates a network at sample distances ``t`` along rays and composites them (``volume.composite``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from jaxtyping import Bool, Float, Int
from torch import Tensor

from depthnerf.bundles import FieldFn, TensorBundle
from depthnerf.render.noise import Generators, normal
from depthnerf.render.rays import RayBundle
from depthnerf.render.volume import RenderResult


@dataclass
class RenderOutput(TensorBundle):
    """Results of both passes; ``fine`` is None when no fine network was given (paper path)."""

    coarse: RenderResult
    """Coarse pass (or pass 1 of the depth-guided sampler)."""
    fine: RenderResult | None
    """Fine pass (or pass 2 of the depth-guided sampler, which always exists)."""

    @property
    def final(self) -> RenderResult:
        """The result an image is made of: fine if present, else coarse."""
        return self.fine if self.fine is not None else self.coarse


def evaluate_field(field: FieldFn, rays: RayBundle, t: Float[Tensor, "B R S"]
                   ) -> tuple[Float[Tensor, "B R S 3"], Float[Tensor, "B R S"]]:
    """Call ``field`` at the points ``o + t d`` with the rays' directions, checking the returned shapes."""
    rgb, sigma = field(rays.points(t), rays.directions)
    if rgb.shape != (*t.shape, 3) or sigma.shape != t.shape:
        raise ValueError(f"field returned rgb {tuple(rgb.shape)} and sigma {tuple(sigma.shape)} for samples "
                         f"{tuple(t.shape)}; expected {(*t.shape, 3)} and {tuple(t.shape)}")
    return rgb, sigma


def add_sigma_noise(sigma: Tensor, std: float, train: bool, generator: Generators,
                    eps: Tensor | None = None) -> Tensor:
    """``sigma + std * eps`` in training when ``std > 0`` (pixelNeRF ``noise_std``), else ``sigma``; ``eps ~ N(0,
    1)`` of sigma's shape, the given one or drawn from ``generator``."""
    if not train or std <= 0:
        return sigma
    if eps is None:
        eps = normal(tuple(sigma.shape), generator, dtype=sigma.dtype, device=sigma.device)
    return sigma + std * eps


def sorted_union(t: Tensor, *values: Tensor) -> tuple[Tensor, ...]:
    """Sort ``t`` along the sample axis and gather ``values`` (``[..., S]`` or ``[..., S, C]``) the same way."""
    t_sorted, order = torch.sort(t, dim=-1)
    out = [t_sorted]
    for v in values:
        idx = order if v.ndim == t.ndim else order[..., None].expand(*order.shape, v.shape[-1])
        out.append(torch.gather(v, t.ndim - 1, idx))
    return tuple(out)


def cat_results(parts: list[RenderResult], dim: int = 1) -> RenderResult:
    """Concatenate results along the ray axis (``dim=1``)."""
    return RenderResult.cat(parts, dim=dim)


def group_indices(member: Bool[Tensor, "B R"]) -> tuple[Int[Tensor, "B G"], Bool[Tensor, "B G"]]:
    """Per batch row, the indices of the ``True`` rays first (stable), cut to ``G`` = the largest count.

    Returns the indices and which of them are real members (rows with fewer members are padded with
    non-members, whose results the caller discards).
    """
    count = member.sum(1)
    order = torch.argsort((~member).to(torch.uint8), dim=1, stable=True)
    g = int(count.max()) if member.numel() else 0
    keep = torch.arange(g, device=member.device)[None, :] < count[:, None]
    return order[:, :g], keep


def scatter_result(dest: RenderResult, src: RenderResult, idx: Int[Tensor, "B G"], keep: Bool[Tensor, "B G"],
                   far: Float[Tensor, "B R"]) -> None:
    """Write the kept rays of ``src`` into ``dest`` (in place); samples beyond ``src``'s count are padded
    with ``t = far`` and zero weight."""
    rows = torch.arange(idx.shape[0], device=idx.device)[:, None].expand_as(idx)[keep]
    cols = idx[keep]
    s_src = src.t.shape[-1]
    dest.rgb[rows, cols] = src.rgb[keep]
    dest.distance[rows, cols] = src.distance[keep]
    dest.opacity[rows, cols] = src.opacity[keep]
    dest.weights[rows, cols] = 0.0
    dest.weights[rows, cols, :s_src] = src.weights[keep]
    dest.t[rows, cols] = far[rows, cols][:, None]
    dest.t[rows, cols, :s_src] = src.t[keep]


def empty_result(shape: tuple[int, int], samples: int, like: Tensor) -> RenderResult:
    """A zero-filled result for ``shape = (B, R)`` rays with ``samples`` samples each."""
    z = like.new_zeros
    return RenderResult(rgb=z(*shape, 3), distance=z(*shape), opacity=z(*shape), weights=z(*shape, samples),
                        t=z(*shape, samples))
