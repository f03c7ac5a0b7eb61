"""Volume rendering (alpha compositing) as pure functions, following pixelNeRF's ``composite``.

For one ray with sorted sample distances ``t_0 <= ... <= t_{S-1}`` inside ``[near, far]``, density ``sigma_i >= 0``
(negative raw values are clamped by ReLU as pixelNeRF does) and colour ``c_i``::

    delta_i = t_{i+1} - t_i,   delta_{S-1} = far - t_{S-1}       (pixelNeRF's ``delta_inf``: the last sample
                                                                   stands for the interval up to far)
    alpha_i = 1 - exp(-sigma_i delta_i)
    T_i     = prod_{j<i} (1 - alpha_j) = exp(-sum_{j<i} sigma_j delta_j)     (transmittance before sample i)
    w_i     = alpha_i T_i
    opacity = sum_i w_i = 1 - T_S
    rgb     = sum_i w_i c_i  (+ 1 - opacity on a white background)
    distance = sum_i w_i t_i                                     (expected ray distance, NOT divided by opacity,
                                                                  so it tends to 0 on empty rays, as pixelNeRF)

``T`` is computed as ``exp`` of an exclusive cumulative sum of optical depths, which equals pixelNeRF's
``cumprod(1 - alpha + 1e-10)`` up to that 1e-10 and does not lose precision on long products.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from jaxtyping import Float
from torch import Tensor

from depthnerf.bundles import TensorBundle


@dataclass
class RenderResult(TensorBundle):
    """Composited output of one pass (coarse or fine) for ``B x R`` rays with ``S`` samples each."""

    rgb: Float[Tensor, "B R 3"]
    """Pixel colour, including the white background if configured."""
    distance: Float[Tensor, "B R"]
    """Expected ray distance ``sum w_i t_i`` (not normalised by opacity; not z-depth: ``depthnerf.data.cameras``)."""
    opacity: Float[Tensor, "B R"]
    """Accumulated opacity ``sum w_i`` in [0, 1]."""
    weights: Float[Tensor, "B R S"]
    """Compositing weights ``w_i``."""
    t: Float[Tensor, "B R S"]
    """Sorted sample ray distances."""

    def normalized_distance(self, eps: float = 1e-10) -> Float[Tensor, "B R"]:
        """``distance / opacity``: the expected ray distance of the visible surface (meaningless where opacity
        ~ 0)."""
        return self.distance / self.opacity.clamp_min(eps)


def compute_deltas(t: Float[Tensor, "*N S"], far: Float[Tensor, "*N"]) -> Float[Tensor, "*N S"]:
    """Interval lengths ``t_{i+1} - t_i``, the last one ``far - t_{S-1}``."""
    return torch.cat([t[..., 1:] - t[..., :-1], far[..., None] - t[..., -1:]], dim=-1)


def render_weights(sigma: Float[Tensor, "*N S"], deltas: Float[Tensor, "*N S"]
                   ) -> tuple[Float[Tensor, "*N S"], Float[Tensor, "*N S"]]:
    """Compositing weights ``w_i = alpha_i T_i`` and transmittances ``T_i`` from densities and interval lengths."""
    tau = torch.relu(sigma) * deltas
    alpha = 1.0 - torch.exp(-tau)
    excl = torch.cat([torch.zeros_like(tau[..., :1]), torch.cumsum(tau[..., :-1], dim=-1)], dim=-1)
    trans = torch.exp(-excl)
    return alpha * trans, trans


def composite(t: Float[Tensor, "B R S"], far: Float[Tensor, "B R"], sigma: Float[Tensor, "B R S"],
              rgb: Float[Tensor, "B R S 3"], *, white_background: bool) -> RenderResult:
    """Alpha-composite samples into pixel colour, expected ray distance and opacity (formulas in the module
    docstring)."""
    weights, _ = render_weights(sigma, compute_deltas(t, far))
    opacity = weights.sum(-1)
    color = (weights[..., None] * rgb).sum(-2)
    if white_background:
        color = color + (1.0 - opacity)[..., None]
    return RenderResult(rgb=color, distance=(weights * t).sum(-1), opacity=opacity, weights=weights, t=t)
