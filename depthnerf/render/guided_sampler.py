"""The depth-guided sampler (beyond the paper): two passes of one network around a per-ray ``DepthGuide``.

See :class:`~depthnerf.render.config.GuidedConfig` for the sample counts and
:mod:`depthnerf.render.depth_guide` for how guesses are made. Rays are split into the guide's *occupied* and *empty*
groups, each rendered with its own sample counts (per batch row, padded to the largest group), and the results
are scattered back; sample axes shorter than the widest group are padded with ``t = far`` and zero weight.
"""

from __future__ import annotations

import torch
from jaxtyping import Float
from torch import Tensor

from depthnerf.render.config import RenderConfig
from depthnerf.render.depth_guide import DepthGuide
from depthnerf.render.noise import Generators
from depthnerf.render.passes import (
    FieldFn,
    RenderOutput,
    add_sigma_noise,
    empty_result,
    evaluate_field,
    group_indices,
    scatter_result,
    sorted_union,
)
from depthnerf.render.rays import RayBundle
from depthnerf.render.samplers import gap_bins, gaussian_samples, sample_pdf, stratified_samples
from depthnerf.render.volume import RenderResult, composite


def guided_first_samples(rays: RayBundle, guide: DepthGuide, n_uniform: int, n_window: int, *, random: bool,
                         generator: Generators = None) -> Float[Tensor, "B R S"]:
    """Pass-1 samples of occupied rays, sorted, ``S = n_uniform + n_window``: ``n_uniform`` stratified over
    [near, far] and ``n_window`` stratified over the guide's window (:meth:`DepthGuide.window`)."""
    lo, hi = guide.window(rays.near, rays.far)
    t_u = stratified_samples(rays.near, rays.far, n_uniform, random=random, generator=generator)
    # eval: a quarter-bin offset keeps the two stratified sets from coinciding when the window is [near, far]
    t_w = stratified_samples(lo, hi, n_window, random=random, generator=generator, eval_offset=0.25)
    return torch.sort(torch.cat([t_u, t_w], dim=-1), dim=-1).values


def _two_pass(net1: FieldFn, net2: FieldFn, reuse: bool, rays: RayBundle, t1: Tensor, n_importance: int,
              n_gaussian: int, cfg: RenderConfig, train: bool, random: bool,
              generator: Generators) -> tuple[RenderResult, RenderResult]:
    gc = cfg.guided
    rgb1, sigma1 = evaluate_field(net1, rays, t1)
    sigma1 = add_sigma_noise(sigma1, cfg.sigma_noise_std, train, generator)
    res1 = composite(t1, rays.far, sigma1, rgb1, white_background=cfg.white_background)
    parts = []
    if n_importance > 0:
        edges, masses = gap_bins(t1, res1.weights, rays.near, rays.far)
        parts.append(sample_pdf(edges, masses, n_importance, random=random, generator=generator,
                                epsilon=gc.pdf_epsilon))
    if n_gaussian > 0:
        parts.append(gaussian_samples(res1.normalized_distance().detach(), rays.near, rays.far, n_gaussian,
                                      gc.gaussian_std, random=random, generator=generator))
    if not parts:
        if reuse:
            return res1, res1
        rgb2, sigma2 = evaluate_field(net2, rays, t1)
        sigma2 = add_sigma_noise(sigma2, cfg.sigma_noise_std, train, generator)
        return res1, composite(t1, rays.far, sigma2, rgb2, white_background=cfg.white_background)
    t_new = torch.cat(parts, dim=-1)
    if reuse:
        rgb_new, sigma_new = evaluate_field(net2, rays, t_new)
        sigma_new = add_sigma_noise(sigma_new, cfg.sigma_noise_std, train, generator)
        t2, sigma2, rgb2 = sorted_union(torch.cat([t1, t_new], -1), torch.cat([sigma1, sigma_new], -1),
                                        torch.cat([rgb1, rgb_new], -2))
    else:
        t2 = torch.sort(torch.cat([t1, t_new], -1), dim=-1).values
        rgb2, sigma2 = evaluate_field(net2, rays, t2)
        sigma2 = add_sigma_noise(sigma2, cfg.sigma_noise_std, train, generator)
    return res1, composite(t2, rays.far, sigma2, rgb2, white_background=cfg.white_background)


def _gather_rays(rays: RayBundle, idx: Tensor) -> RayBundle:
    vec = idx[..., None].expand(*idx.shape, 3)
    return RayBundle(torch.gather(rays.origins, 1, vec), torch.gather(rays.directions, 1, vec),
                     torch.gather(rays.near, 1, idx), torch.gather(rays.far, 1, idx))


def render_guided(coarse: FieldFn, fine: FieldFn | None, rays: RayBundle, cfg: RenderConfig, *, train: bool,
                  generator: Generators, guide: DepthGuide) -> RenderOutput:
    """Depth-guided render of ``B x R`` rays; ``coarse`` = pass 1, ``fine`` = pass 2 (both always present)."""
    gc = cfg.guided
    random = train or cfg.sampler.eval_random
    net2 = fine if fine is not None else coarse
    reuse = gc.first_pass == "fine" or fine is None
    net1 = net2 if reuse else coarse
    n1_occ, n1_emp = gc.n_uniform + gc.n_window, gc.n_empty
    n2_occ, n2_emp = n1_occ + gc.n_importance + gc.n_gaussian, n1_emp + gc.n_empty_importance
    groups = [(True, guide.occupied, gc.n_importance, gc.n_gaussian),
              (False, ~guide.occupied, gc.n_empty_importance, 0)]
    shape = tuple(rays.near.shape)
    out1 = empty_result(shape, max(n1_occ, n1_emp), rays.near)
    out2 = empty_result(shape, max(n2_occ, n2_emp), rays.near)
    for occupied, member, n_imp, n_gauss in groups:
        idx, keep = group_indices(member)
        if idx.shape[1] == 0:
            continue
        sub_rays, sub_guide = _gather_rays(rays, idx), guide.gather(idx)
        if occupied:
            t1 = guided_first_samples(sub_rays, sub_guide, gc.n_uniform, gc.n_window, random=random,
                                      generator=generator)
        else:
            t1 = stratified_samples(sub_rays.near, sub_rays.far, n1_emp, random=random, generator=generator)
        res1, res2 = _two_pass(net1, net2, reuse, sub_rays, t1, n_imp, n_gauss, cfg, train, random, generator)
        scatter_result(out1, res1, idx, keep, rays.far)
        scatter_result(out2, res2, idx, keep, rays.far)
    return RenderOutput(coarse=out1, fine=out2)
