"""Depth guides from a source view and the depth-guided sampler on analytic sphere scenes."""

import math
import statistics

import pytest
import torch

from depthnerf.data.cameras import Intrinsics, look_at
from depthnerf.depth.normalize import normalize_disparity
from depthnerf.render.analytic import Sphere, SphereScene
from depthnerf.render.config import GuidedConfig, RenderConfig, SamplerConfig
from depthnerf.render.depth_guide import DepthGuide, align_disparity_to_depth, build_depth_guide
from depthnerf.render.guided_sampler import guided_first_samples
from depthnerf.render.pipeline import render_image, render_rays
from depthnerf.render.rays import RayBundle, camera_z_of_directions, rays_from_camera

NEAR, FAR = 0.8, 1.8
INTR = Intrinsics(131.25, 63.5, 63.5, 128, 128).resized(32, 32)
SCENE = SphereScene((Sphere((0.0, 0.0, 0.0), 0.35), Sphere((0.25, 0.3, 0.15), 0.15)), beta=0.005)


def _camera(az: float, el: float, r: float = 1.3) -> torch.Tensor:
    a, e = math.radians(az), math.radians(el)
    return look_at(torch.tensor([[r * math.cos(e) * math.cos(a), r * math.cos(e) * math.sin(a), r * math.sin(e)]]))


def _psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return -10 * math.log10(((a - b) ** 2).mean().item())


class _Counter:
    """Counts network evaluations (points) of a field."""

    def __init__(self, field):
        self.field, self.points = field, 0

    def __call__(self, pts, dirs):
        self.points += pts.shape[:-1].numel()
        return self.field(pts, dirs)


def _reference(scene, rays):
    return render_rays(scene, None, rays, RenderConfig(sampler=SamplerConfig(n_coarse=4096)), train=False).coarse


def _guide(scene, src, rays, depth=None):
    z, mask = scene.depth_map(src, INTR, NEAR, FAR)
    return build_depth_guide(src, INTR, z if depth is None else depth, mask, rays, GuidedConfig())


def test_guide_classes_against_exact_geometry():
    src, tgt = _camera(0, 20), _camera(25, 35)
    rays = rays_from_camera(tgt, INTR, NEAR, FAR)
    guide = _guide(SCENE, src, rays)
    t_true, hit = SCENE.ray_hits(rays)
    ref = _reference(SCENE, rays)
    assert guide.valid.float().mean() > 0.1
    assert torch.all(guide.valid <= guide.occupied)
    err = (guide.t_guess - t_true).abs()[guide.valid & hit]
    assert err.median() < 0.01 and (err < 0.05).float().mean() > 0.97
    # every ray the source calls empty renders (almost) nothing
    assert ref.opacity[~guide.occupied].max() < 0.01
    assert (~guide.occupied).float().mean() > 0.3  # and there are many of them to save on
    lo, hi = guide.window(rays.near, rays.far)
    assert torch.all(lo <= hi)
    inside = (t_true >= lo) & (t_true <= hi)
    assert inside[guide.valid & hit].float().mean() > 0.97


def test_guided_sampling_matches_full_sampling_with_a_third_of_the_evaluations():
    src, tgt = _camera(0, 20), _camera(40, 30)
    rays = rays_from_camera(tgt, INTR, NEAR, FAR)
    ref = _reference(SCENE, rays)
    full_net = _Counter(SCENE)
    full = render_rays(full_net, full_net, rays, RenderConfig(), train=False)
    guided_net = _Counter(SCENE)
    cfg = RenderConfig(guided=GuidedConfig(enabled=True))
    guided = render_rays(guided_net, guided_net, rays, cfg, train=False, guide=_guide(SCENE, src, rays))
    assert full_net.points == 160 * rays.near.numel()
    assert guided_net.points * 3 <= full_net.points
    p_full, p_guided = _psnr(full.fine.rgb, ref.rgb), _psnr(guided.fine.rgb, ref.rgb)
    assert p_guided > 42 and p_guided > p_full - 6, (p_full, p_guided)
    assert _psnr(guided.fine.rgb, full.fine.rgb) > 42
    # the same budget without the guide's windows (all rays occupied, no trusted guess) is not better
    blind = DepthGuide(rays.near.clone(), rays.near.clone(), torch.zeros_like(rays.near, dtype=torch.bool),
                       torch.ones_like(rays.near, dtype=torch.bool), torch.full_like(rays.near, 0.1))
    blind_out = render_rays(SCENE, SCENE, rays, cfg, train=False, guide=blind)
    assert p_guided > _psnr(blind_out.fine.rgb, ref.rgb) - 0.5


def test_guided_end_to_end_from_a_relative_disparity_prior():
    """Prior = normalised affine disparity of the source; metric scale from a cheap coarse render of the source."""
    src, tgt = _camera(0, 20), _camera(-35, 40)
    z_src, mask = SCENE.depth_map(src, INTR, NEAR, FAR)
    prior = normalize_disparity(torch.where(mask, 0.37 / z_src.clamp_min(1e-3) + 2.0, torch.zeros_like(z_src)), mask)
    src_rays = rays_from_camera(src, INTR, NEAR, FAR)
    cheap = render_image(SCENE, None, src_rays, RenderConfig(sampler=SamplerConfig(n_coarse=32)), chunk=4096).coarse
    ref_z = (cheap.normalized_distance() * camera_z_of_directions(src_rays.directions, src)).reshape(1, 32, 32)
    fit_mask = mask & (cheap.opacity > 0.9).reshape(1, 32, 32)
    aligned = align_disparity_to_depth(prior, ref_z, fit_mask)
    rel = ((aligned - z_src).abs() / z_src)[mask]
    assert rel.median() < 0.02  # coarse 32-sample reference is biased by about half a bin
    rays = rays_from_camera(tgt, INTR, NEAR, FAR)
    guide = build_depth_guide(src, INTR, aligned, mask, rays, GuidedConfig())
    cfg = RenderConfig(guided=GuidedConfig(enabled=True))
    out = render_image(SCENE, SCENE, rays, cfg, chunk=4096, guide=guide)
    assert _psnr(out.fine.rgb, _reference(SCENE, rays).rgb) > 42


def test_guided_sampling_is_robust_to_surfaces_hidden_from_the_source():
    """A small sphere hidden behind a big one from the source is seen from the side by the target."""
    scene = SphereScene((Sphere((0.0, 0.0, 0.0), 0.25), Sphere((-0.3, 0.0, 0.05), 0.12)), beta=0.005)
    src, tgt = _camera(0, 5), _camera(90, 10)
    rays = rays_from_camera(tgt, INTR, NEAR, FAR)
    hidden_z, _ = scene.depth_map(src, INTR, NEAR, FAR)
    small = SphereScene((Sphere((-0.3, 0.0, 0.05), 0.12),))
    t_small, hits_small = small.ray_hits(rays)
    t_all, _ = scene.ray_hits(rays)
    on_hidden = hits_small & ((t_all - t_small).abs() < 1e-6)  # target sees the hidden sphere here
    assert on_hidden.sum() > 10
    guide = _guide(scene, src, rays, hidden_z)
    assert not guide.valid[on_hidden].any() and guide.occupied[on_hidden].all()  # shadow entries
    ref = _reference(scene, rays)
    out = render_rays(scene, scene, rays, RenderConfig(guided=GuidedConfig(enabled=True)), train=False,
                      guide=guide)
    err = ((out.fine.rgb - ref.rgb) ** 2).mean(-1)
    assert -10 * math.log10(err[on_hidden].mean().item()) > 35
    assert _psnr(out.fine.rgb, ref.rgb) > 40


def test_guided_batch_rows_with_different_group_sizes_match_single_rows():
    src = torch.cat([_camera(0, 20), _camera(180, 30)])
    tgt = torch.cat([_camera(30, 30), _camera(150, 20)])
    rays = rays_from_camera(tgt, INTR, NEAR, FAR)
    z, mask = SCENE.depth_map(src, INTR, NEAR, FAR)
    guide = build_depth_guide(src, INTR, z, mask, rays, GuidedConfig())
    assert guide.occupied[0].sum() != guide.occupied[1].sum()
    cfg = RenderConfig(guided=GuidedConfig(enabled=True))
    both = render_rays(SCENE, SCENE, rays, cfg, train=False, guide=guide)
    for b in range(2):
        row = RayBundle(rays.origins[b:b + 1], rays.directions[b:b + 1], rays.near[b:b + 1], rays.far[b:b + 1])
        row_guide = build_depth_guide(src[b:b + 1], INTR, z[b:b + 1], mask[b:b + 1], row, GuidedConfig())
        single = render_rays(SCENE, SCENE, row, cfg, train=False, guide=row_guide)
        assert torch.allclose(both.fine.rgb[b], single.fine.rgb[0], atol=1e-6)
        s = single.fine.t.shape[-1]
        assert torch.allclose(both.fine.t[b, :, :s], single.fine.t[0], atol=1e-6)
        assert torch.all(both.fine.weights[b, :, s:] == 0)


def test_guided_training_pass_is_differentiable():
    field = torch.nn.Linear(3, 4)

    def fn(pts, dirs):
        h = field(pts)
        return torch.sigmoid(h[..., :3]), torch.nn.functional.softplus(h[..., 3]) * 5

    src, tgt = _camera(0, 20), _camera(40, 30)
    rays = rays_from_camera(tgt, INTR, NEAR, FAR)
    cfg = RenderConfig(guided=GuidedConfig(enabled=True))
    out = render_rays(fn, fn, rays, cfg, train=True, generator=torch.Generator().manual_seed(0),
                      guide=_guide(SCENE, src, rays))
    out.fine.rgb.sum().backward()
    assert field.weight.grad.abs().sum() > 0


def test_guide_input_checks():
    rays = rays_from_camera(_camera(40, 30), INTR, NEAR, FAR)
    z, mask = SCENE.depth_map(_camera(0, 20), INTR, NEAR, FAR)
    with pytest.raises(ValueError, match="disagree"):
        build_depth_guide(_camera(0, 20), INTR, z[:, :16], mask[:, :16], rays, GuidedConfig())
    guide = build_depth_guide(_camera(0, 20), INTR, z, mask, rays, GuidedConfig())
    with pytest.raises(ValueError, match="DepthGuide"):
        render_rays(SCENE, SCENE, rays, RenderConfig(), train=False, guide=guide)
    with pytest.raises(ValueError, match="guide for"):
        render_rays(SCENE, SCENE, rays.slice(0, 10), RenderConfig(guided=GuidedConfig(enabled=True)),
                    train=False, guide=guide)


def _axis_rays(r: int) -> RayBundle:
    """``r`` rays from the origin along +z, t in [0.8, 1.8] (double precision)."""
    dirs = torch.zeros(1, r, 3, dtype=torch.float64)
    dirs[..., 2] = 1.0
    return RayBundle(torch.zeros_like(dirs), dirs, torch.full((1, r), NEAR, dtype=torch.float64),
                     torch.full((1, r), FAR, dtype=torch.float64))


def _slab_field(pts, dirs):
    """Density 5 on 1.25 < z < 1.35 (optical depth 0.5 along +z, opacity 1 - e^-0.5 ~ 0.39), grey colour."""
    sigma = torch.where((pts[..., 2] - 1.3).abs() < 0.05, 5.0, 0.0).to(pts.dtype)
    return torch.full((*pts.shape[:-1], 3), 0.5, dtype=pts.dtype), sigma


def _trusted_guide(t_guess: float, spread: float, r: int, valid: bool = True) -> DepthGuide:
    full = torch.full((1, r), t_guess, dtype=torch.float64)
    flag = torch.full((1, r), valid)
    return DepthGuide(full, full - spread, flag, torch.ones(1, r, dtype=torch.bool),
                      torch.full((1, r), spread, dtype=torch.float64))


def test_first_pass_samples_are_the_uniform_bins_and_the_window_bins():
    """Evaluation samples: midpoints of ``n_uniform`` bins of [near, far] and the points at a quarter of each of
    ``n_window`` bins of the window, [t_guess - spread, t_guess + spread] on a trusted ray, [t_enter, far] else."""
    rays = _axis_rays(2)
    guide = _trusted_guide(1.3, 0.1, 2)
    guide.valid[0, 1] = False  # untrusted: window from t_enter = 1.2 to far
    t = guided_first_samples(rays, guide, 4, 6, random=False)
    for r, (lo, hi) in enumerate(((1.2, 1.4), (1.2, FAR))):
        uniform = [NEAR + (k + 0.5) * (FAR - NEAR) / 4 for k in range(4)]
        window = [lo + (k + 0.25) * (hi - lo) / 6 for k in range(6)]
        assert torch.allclose(t[0, r], torch.tensor(sorted(uniform + window), dtype=torch.float64), atol=1e-12)


def test_gaussian_samples_centre_on_the_opacity_normalised_first_pass_depth():
    """Half-transparent slab: pass 2 adds ``n_gaussian`` samples ``c + std * Phi^-1((k + 0.5) / n)`` around
    ``c = sum w t / sum w`` of pass 1 (near the slab at 1.3), not around ``sum w t`` (~0.39 * 1.3)."""
    rays = _axis_rays(1)
    cfg = RenderConfig(guided=GuidedConfig(enabled=True, n_importance=0, n_gaussian=8))
    out = render_rays(_slab_field, _slab_field, rays, cfg, train=False, guide=_trusted_guide(1.3, 0.1, 1))
    w, t1 = out.coarse.weights[0, 0], out.coarse.t[0, 0]
    assert 0.3 < w.sum() < 0.5  # pass 1 sees a partly transparent surface
    centre = (w * t1).sum() / w.sum()
    assert abs(centre - 1.3) < 0.05
    normal = statistics.NormalDist()
    gauss = [float(centre) + 0.01 * normal.inv_cdf((k + 0.5) / 8) for k in range(8)]
    expect = torch.sort(torch.cat([t1, torch.tensor(gauss, dtype=torch.float64)])).values
    assert torch.allclose(out.fine.t[0, 0], expect, atol=1e-9)


def test_without_a_fine_network_pass_two_reuses_pass_one_for_either_first_pass():
    """Evaluations per occupied ray: n_uniform + n_window (pass 1) + n_importance + n_gaussian (pass 2 only)."""
    rays = _axis_rays(3)
    gc = GuidedConfig(enabled=True)
    per_ray = gc.n_uniform + gc.n_window + gc.n_importance + gc.n_gaussian
    renders = []
    for first_pass in ("fine", "coarse"):
        net = _Counter(_slab_field)
        cfg = RenderConfig(guided=GuidedConfig(enabled=True, first_pass=first_pass))
        renders.append(render_rays(net, None, rays, cfg, train=False, guide=_trusted_guide(1.3, 0.1, 3)))
        assert net.points == 3 * per_ray, first_pass
    assert torch.equal(renders[0].fine.rgb, renders[1].fine.rgb)


def test_guided_evaluation_honours_eval_random():
    rays = _axis_rays(4)
    guide = _trusted_guide(1.3, 0.1, 4)

    def render(eval_random: bool, seed: int):
        cfg = RenderConfig(sampler=SamplerConfig(eval_random=eval_random), guided=GuidedConfig(enabled=True))
        return render_rays(_slab_field, _slab_field, rays, cfg, train=False,
                           generator=torch.Generator().manual_seed(seed), guide=guide).coarse.t

    assert torch.equal(render(False, 0), render(False, 1))  # deterministic: the generator is not used
    assert torch.equal(render(True, 0), render(True, 0)) and not torch.equal(render(True, 0), render(True, 1))
    assert not torch.equal(render(True, 0), render(False, 0))
