"""Coarse/fine orchestration (the paper's sampler and the depth-guided one) and chunked image rendering.

The networks are passed in as :data:`FieldFn` callables; nothing here holds state. The paper's path (pixelNeRF)::

    t_c  = stratified(near, far, 64)                       -> coarse net -> composite -> coarse result
    t_i  = sample_pdf(uniform coarse bins, coarse weights, 16)
    t_g  = clamp(coarse distance + 0.01 N(0, 1), near, far)  x 16
    t_f  = sort(t_c ++ t_i ++ t_g)   (96 samples)          -> fine net   -> composite -> fine result

As in pixelNeRF the fine pass re-evaluates the coarse samples with the fine network (``z_combine`` includes
``z_coarse``), the Gaussian centre is the *unnormalised* coarse ray distance ``sum w t``
(``RenderResult.distance``; so empty rays put those samples at near) and is not detached
(``SamplerConfig.detach_gaussian_center``). One deliberate difference: pixelNeRF draws random samples at evaluation
too; here ``train=False`` is deterministic (bin midpoints, quantiles; see
``samplers``) unless ``SamplerConfig.eval_random``. The depth-guided path (``cfg.guided.enabled``) is in
:mod:`~depthnerf.render.guided_sampler`.
"""

from __future__ import annotations

import torch

from depthnerf.render.config import RenderConfig
from depthnerf.render.depth_guide import DepthGuide
from depthnerf.render.draws import PaperDraws, draw_paper
from depthnerf.render.guided_sampler import render_guided
from depthnerf.render.noise import Generators
from depthnerf.render.passes import FieldFn, RenderOutput, add_sigma_noise, cat_results, evaluate_field
from depthnerf.render.rays import RayBundle
from depthnerf.render.samplers import gaussian_samples, sample_pdf, stratified_samples, uniform_bin_edges
from depthnerf.render.volume import composite

__all__ = ["FieldFn", "RenderOutput", "render_image", "render_rays"]


def _render_paper(coarse: FieldFn, fine: FieldFn | None, rays: RayBundle, cfg: RenderConfig, train: bool,
                  generator: Generators, draws: PaperDraws | None) -> RenderOutput:
    sc = cfg.sampler
    random = train or sc.eval_random
    if random and draws is None:
        draws = draw_paper(tuple(rays.near.shape), cfg, fine=fine is not None, sigma_noise=train,
                           generator=generator, dtype=rays.near.dtype, device=rays.near.device)
    jitter, sigma_noise_c, u_importance, eps_gaussian, sigma_noise_f = (
        (draws.coarse_jitter, draws.coarse_sigma, draws.importance, draws.gaussian, draws.fine_sigma) if random
        else (None,) * 5)  # deterministic sampling draws nothing
    t_c = stratified_samples(rays.near, rays.far, sc.n_coarse, random=random, u=jitter)
    rgb_c, sigma_c = evaluate_field(coarse, rays, t_c)
    res_c = composite(t_c, rays.far, add_sigma_noise(sigma_c, cfg.sigma_noise_std, train, None,
                                                     sigma_noise_c), rgb_c,
                      white_background=cfg.white_background)
    if fine is None:
        return RenderOutput(coarse=res_c, fine=None)
    parts = [t_c]
    if sc.n_importance > 0:
        edges = uniform_bin_edges(rays.near, rays.far, sc.n_coarse)
        parts.append(sample_pdf(edges, res_c.weights, sc.n_importance, random=random, epsilon=sc.pdf_epsilon,
                                u=u_importance))
    if sc.n_gaussian > 0:
        center = res_c.distance.detach() if sc.detach_gaussian_center else res_c.distance
        parts.append(gaussian_samples(center, rays.near, rays.far, sc.n_gaussian, sc.gaussian_std,
                                      random=random, eps=eps_gaussian))
    t_f, _ = torch.sort(torch.cat(parts, dim=-1), dim=-1)
    rgb_f, sigma_f = evaluate_field(fine, rays, t_f)
    res_f = composite(t_f, rays.far, add_sigma_noise(sigma_f, cfg.sigma_noise_std, train, None,
                                                     sigma_noise_f), rgb_f,
                      white_background=cfg.white_background)
    return RenderOutput(coarse=res_c, fine=res_f)


def render_rays(coarse: FieldFn, fine: FieldFn | None, rays: RayBundle, cfg: RenderConfig, *, train: bool,
                generator: Generators = None, guide: DepthGuide | None = None,
                draws: PaperDraws | None = None) -> RenderOutput:
    """Render ``B x R`` rays with the paper's sampler, or the depth-guided one if ``cfg.guided.enabled``.

    ``train`` switches random sampling and sigma noise on; ``generator`` makes the draws reproducible, or
    ``draws`` gives them (the paper's sampler only; :func:`~depthnerf.render.draws.draw_paper` with the same
    generator gives the same render bit for bit). A ``guide`` is required exactly when ``cfg.guided.enabled``
    (passing one otherwise is an error, never ignored). Differentiable with respect to the networks' outputs.
    """
    if cfg.guided.enabled != (guide is not None):
        raise ValueError("render_rays: a DepthGuide must be given exactly when cfg.guided.enabled is True "
                         f"(enabled={cfg.guided.enabled}, guide given={guide is not None})")
    if draws is not None and (guide is not None or generator is not None):
        raise ValueError("render_rays: pre-drawn draws are for the paper's sampler, without a generator or guide")
    if guide is not None:
        if guide.t_guess.shape != rays.near.shape:
            raise ValueError(f"render_rays: guide for {tuple(guide.t_guess.shape)} rays, "
                             f"rays are {tuple(rays.near.shape)}")
        return render_guided(coarse, fine, rays, cfg, train=train, generator=generator, guide=guide)
    return _render_paper(coarse, fine, rays, cfg, train, generator, draws)


@torch.no_grad()
def render_image(coarse: FieldFn, fine: FieldFn | None, rays: RayBundle, cfg: RenderConfig, *, chunk: int,
                 generator: Generators = None, guide: DepthGuide | None = None) -> RenderOutput:
    """Evaluation render of many rays (e.g. ``R = H * W``) in chunks of ``chunk`` rays per batch element.

    No gradients, ``train=False``; identical to one ``render_rays`` call over all rays when sampling is
    deterministic (the default). The caller reshapes ``[B, H*W, ...]`` outputs to images.
    """
    if chunk <= 0:
        raise ValueError(f"render_image: chunk must be positive, got {chunk}")
    outs = []
    for start in range(0, rays.num_rays, chunk):
        stop = min(start + chunk, rays.num_rays)
        sub_guide = guide.slice(start, stop) if guide is not None else None
        outs.append(render_rays(coarse, fine, rays.slice(start, stop), cfg, train=False, generator=generator,
                                guide=sub_guide))
    fine_parts = [o.fine for o in outs if o.fine is not None]
    return RenderOutput(coarse=cat_results([o.coarse for o in outs]),
                        fine=cat_results(fine_parts) if fine_parts else None)
