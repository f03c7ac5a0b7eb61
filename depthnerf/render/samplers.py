"""Samplers of ray distances ``t``: stratified, inverse-CDF (importance) and Gaussian, batched over rays.

Every sampler takes ``random``: True draws (training, with an optional ``torch.Generator`` for reproducibility),
False gives the deterministic counterpart used at evaluation (see each function). Facts from pixelNeRF
(``src/render/nerf.py``), which this follows:

- Coarse: ``n`` bins of equal width between near and far, one sample jittered uniformly inside each bin. pixelNeRF
  jitters at evaluation too; here evaluation uses the bin **midpoints** (the mean of the jittered sample), so
  evaluation is deterministic and its samples are the expectation of the training samples.
- Importance: pdf ``(w + eps) / sum(w + eps)`` over the coarse **bins** (uniform bins, not the intervals between
  the jittered samples), weights detached, a bin drawn by ``searchsorted`` on the CDF and a point uniform in it.
  Here the point comes from linear inversion of the CDF inside the bin, which has the same distribution as
  pixelNeRF's "bin index + fresh uniform"; evaluation uses the quantiles ``(k + 0.5) / n``.
- Gaussian: ``depth + std * N(0, 1)`` clamped to [near, far]; evaluation uses normal quantiles
  ``Phi^-1((k + 0.5) / n)``, whose mean is exactly ``depth``.
"""

from __future__ import annotations

import torch
from jaxtyping import Float
from torch import Tensor

from depthnerf.render.noise import Generators, normal, uniform


def _quantiles(shape: tuple[int, ...], n: int, *, random: bool, generator: Generators,
               like: Tensor, u: Tensor | None = None) -> Tensor:
    """Uniform [0, 1) variates of shape ``(*shape, n)`` (``u`` if given), or the quantiles ``(k + 0.5) / n``."""
    if random:
        return u if u is not None else uniform((*shape, n), generator, dtype=like.dtype, device=like.device)
    mid = (torch.arange(n, dtype=like.dtype, device=like.device) + 0.5) / n
    return mid.expand(*shape, n)


def stratified_samples(near: Float[Tensor, "*N"], far: Float[Tensor, "*N"], n: int, *, random: bool,
                       generator: Generators = None, eval_offset: float = 0.5,
                       u: Float[Tensor, "*N n"] | None = None) -> Float[Tensor, "*N n"]:
    """One sample per equal bin of ``[near, far]``: bin ``k`` is ``[near + k h, near + (k+1) h]``, ``h = (far -
    near) / n``; uniform inside the bin if ``random`` (at fraction ``u``, drawn from ``generator`` unless given),
    else at fraction ``eval_offset`` of it (0.5: the midpoint, the mean of the random sample). Sorted along the
    last axis."""
    if random:
        frac = u if u is not None else uniform((*near.shape, n), generator, dtype=near.dtype, device=near.device)
    else:
        frac = torch.full((n,), eval_offset, dtype=near.dtype, device=near.device)
    s = (torch.arange(n, dtype=near.dtype, device=near.device) + frac) / n
    return near[..., None] * (1.0 - s) + far[..., None] * s


def uniform_bin_edges(near: Float[Tensor, "*N"], far: Float[Tensor, "*N"], n: int) -> Float[Tensor, "*N n+1"]:
    """Edges of the ``n`` equal bins of ``[near, far]`` (the bins of :func:`stratified_samples`)."""
    s = torch.linspace(0.0, 1.0, n + 1, dtype=near.dtype, device=near.device)
    return near[..., None] * (1.0 - s) + far[..., None] * s


def gap_bins(t: Float[Tensor, "*N S"], weights: Float[Tensor, "*N S"], near: Float[Tensor, "*N"],
             far: Float[Tensor, "*N"]) -> tuple[Float[Tensor, "*N S+2"], Float[Tensor, "*N S+1"]]:
    """Bins between consecutive samples, ``[near, t_0], [t_0, t_1], ..., [t_{S-1}, far]``, with masses
    ``w_0, max(w_0, w_1), ..., max(w_{S-2}, w_{S-1}), w_{S-1}`` (a max-filter of the weights, as mip-NeRF's).

    For non-uniform samples (the depth-guided sampler). Weight ``w_i`` comes from the density at ``t_i`` and is
    spread over ``[t_i, t_{i+1}]`` by the compositing rule, while where the density changes (a surface onset
    before ``t_i``, a decay after it) lies in the gaps on *both* sides; giving each gap the larger of its two
    neighbours' weights puts the new samples in both.
    """
    edges = torch.cat([torch.minimum(near[..., None], t[..., :1]), t,
                       torch.maximum(far[..., None], t[..., -1:])], dim=-1)
    inner = torch.maximum(weights[..., :-1], weights[..., 1:])
    return edges, torch.cat([weights[..., :1], inner, weights[..., -1:]], dim=-1)


def sample_pdf(edges: Float[Tensor, "*N K+1"], weights: Float[Tensor, "*N K"], n: int, *, random: bool,
               generator: Generators = None, epsilon: float = 1e-5,
               u: Float[Tensor, "*N n"] | None = None) -> Float[Tensor, "*N n"]:
    """Inverse-CDF samples of the piecewise-constant pdf with mass ``w_k + epsilon`` on bin ``[e_k, e_{k+1}]``
    (zero-width bins get no mass, so samples never pile up on duplicate edges); a ray with no mass at all (every
    weight 0 with ``epsilon = 0``) gets equal mass on its positive-width bins instead of every sample at its far
    edge.

    ``weights`` are detached (no gradient flows into sample positions). ``u`` is uniform (``random``: the given
    ``u``, else drawn from ``generator``) or the quantiles ``(j + 0.5) / n``; the bin is
    ``searchsorted(cdf, u, right=True) - 1`` and the sample ``e_k + (u - cdf_k) / p_k * (e_{k+1} - e_k)``. Not
    sorted.
    """
    edges = edges.detach()
    width = (edges[..., 1:] > edges[..., :-1]).to(weights.dtype)
    w = (weights.detach() + epsilon) * width
    w = torch.where(w.sum(-1, keepdim=True) > 0, w, width)
    pdf = w / w.sum(-1, keepdim=True).clamp_min(1e-30)
    cdf = torch.cat([torch.zeros_like(pdf[..., :1]), torch.cumsum(pdf, -1)], dim=-1).contiguous()
    u = _quantiles(tuple(weights.shape[:-1]), n, random=random, generator=generator, like=w, u=u).contiguous()
    idx = (torch.searchsorted(cdf, u, right=True) - 1).clamp(0, weights.shape[-1] - 1)
    cdf_lo = torch.gather(cdf, -1, idx)
    p = torch.gather(pdf, -1, idx)
    lo = torch.gather(edges, -1, idx)
    hi = torch.gather(edges, -1, idx + 1)
    frac = ((u - cdf_lo) / p.clamp_min(1e-30)).clamp(0.0, 1.0)
    return lo + frac * (hi - lo)


def gaussian_samples(center: Float[Tensor, "*N"], near: Float[Tensor, "*N"], far: Float[Tensor, "*N"], n: int,
                     std: float, *, random: bool, generator: Generators = None,
                     eps: Float[Tensor, "*N n"] | None = None) -> Float[Tensor, "*N n"]:
    """``center + std * eps`` clamped to ``[near, far]``; ``eps ~ N(0, 1)`` if ``random`` (the given ``eps``,
    else drawn from ``generator``), else the normal quantiles ``Phi^-1((k + 0.5) / n)``. Differentiable in
    ``center`` (pixelNeRF does not detach it)."""
    if random:
        eps = eps if eps is not None else normal((*center.shape, n), generator, dtype=center.dtype,
                                                 device=center.device)
    else:
        q = (torch.arange(n, dtype=torch.float64, device=center.device) + 0.5) / n
        eps = torch.special.ndtri(q).to(center.dtype).expand(*center.shape, n)
    t = center[..., None] + std * eps
    return torch.minimum(torch.maximum(t, near[..., None]), far[..., None])
