"""The random numbers of one random render with the paper's sampler, drawn before the render.

A random render (``train=True``, or ``SamplerConfig.eval_random``) of ``B x R`` rays draws, in this order:

1. ``coarse_jitter``: ``U[0, 1)`` of shape ``(B, R, n_coarse)``, where each coarse sample sits in its bin;
2. ``coarse_sigma``: ``N(0, 1)`` of that shape, the coarse density noise (training with ``sigma_noise_std > 0``);
3. with a fine pass: ``importance``, ``U[0, 1)`` of shape ``(B, R, n_importance)`` (if ``n_importance > 0``),
   then ``gaussian``, ``N(0, 1)`` of shape ``(B, R, n_gaussian)`` (if ``n_gaussian > 0``), then ``fine_sigma``,
   ``N(0, 1)`` of shape ``(B, R, n_coarse + n_importance + n_gaussian)`` (as ``coarse_sigma``).

:func:`draw_paper` makes exactly these draws, in this order and the rays' dtype, from the same generator(s)
(``depthnerf.render.noise``: one per batch row in training). A render given them therefore equals, bit for bit,
one that draws them itself (which is what :func:`~depthnerf.render.pipeline.render_rays` does when given none).
Drawn up front, the render between the draws and the loss holds no generator, so it traces as one graph
(``torch.compile``, CUDA-graph capture): ``depthnerf.train.step``'s compiled step takes them as inputs.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from jaxtyping import Float
from torch import Tensor

from depthnerf.bundles import TensorBundle
from depthnerf.render.config import RenderConfig
from depthnerf.render.noise import Generators, normal, uniform


@dataclass
class PaperDraws(TensorBundle):
    """Pre-drawn variates of one random render with the paper's sampler (module docstring); ``B R`` leading."""

    coarse_jitter: Float[Tensor, "B R Nc"]
    """``U[0, 1)``: each coarse sample's place in its bin (:func:`~depthnerf.render.samplers.stratified_samples`)."""
    coarse_sigma: Float[Tensor, "B R Nc"] | None
    """``N(0, 1)`` density noise of the coarse pass; None without density noise."""
    importance: Float[Tensor, "B R Ni"] | None
    """``U[0, 1)`` inverse-CDF variates (:func:`~depthnerf.render.samplers.sample_pdf`); None without a fine pass
    or importance samples."""
    gaussian: Float[Tensor, "B R Ng"] | None
    """``N(0, 1)`` offsets around the coarse depth (:func:`~depthnerf.render.samplers.gaussian_samples`); None
    without a fine pass or Gaussian samples."""
    fine_sigma: Float[Tensor, "B R Nf"] | None
    """``N(0, 1)`` density noise of the fine pass (``Nf = Nc + Ni + Ng``); None without a fine pass or noise."""


def draw_paper(shape: tuple[int, ...], cfg: RenderConfig, *, fine: bool, sigma_noise: bool, generator: Generators,
               dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> PaperDraws:
    """The draws of one random render of rays of ``shape`` (``(B, R)``): ``fine`` whether there is a fine pass,
    ``sigma_noise`` whether density noise is added (training with ``cfg.sigma_noise_std > 0``)."""
    sc = cfg.sampler
    noise = sigma_noise and cfg.sigma_noise_std > 0

    def u(n: int) -> Tensor:
        return uniform((*shape, n), generator, dtype=dtype, device=device)

    def z(n: int) -> Tensor:
        return normal((*shape, n), generator, dtype=dtype, device=device)

    coarse_jitter = u(sc.n_coarse)
    coarse_sigma = z(sc.n_coarse) if noise else None
    if not fine:
        return PaperDraws(coarse_jitter, coarse_sigma, None, None, None)
    importance = u(sc.n_importance) if sc.n_importance > 0 else None
    gaussian = z(sc.n_gaussian) if sc.n_gaussian > 0 else None
    fine_sigma = z(sc.n_coarse + max(sc.n_importance, 0) + max(sc.n_gaussian, 0)) if noise else None
    return PaperDraws(coarse_jitter, coarse_sigma, importance, gaussian, fine_sigma)
