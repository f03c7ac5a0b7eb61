"""Rays, the paper's coarse/fine orchestration, chunked rendering, gradients."""

import math

import pytest
import torch

from depthnerf.data.cameras import Intrinsics, camera_rays, look_at, ray_distance_to_z, world_to_camera
from depthnerf.render.analytic import Sphere, SphereScene
from depthnerf.render.config import GuidedConfig, RenderConfig, SamplerConfig
from depthnerf.render.depth_guide import build_depth_guide
from depthnerf.render.draws import draw_paper
from depthnerf.render.passes import evaluate_field
from depthnerf.render.pipeline import render_image, render_rays
from depthnerf.render.rays import RayBundle, camera_z_of_directions, rays_from_camera, rays_from_pixels

INTR = Intrinsics(131.25, 63.5, 63.5, 128, 128).resized(24, 24)
SCENE = SphereScene((Sphere((0.0, 0.0, 0.0), 0.35), Sphere((0.25, 0.3, 0.15), 0.15)), beta=0.005)


def _camera(az: float, el: float, r: float = 1.3) -> torch.Tensor:
    a, e = math.radians(az), math.radians(el)
    return look_at(torch.tensor([[r * math.cos(e) * math.cos(a), r * math.cos(e) * math.sin(a), r * math.sin(e)]]))


def _psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return -10 * math.log10(((a - b) ** 2).mean().item())


def test_rays_follow_camera_conventions():
    c2w = torch.cat([_camera(30, 20), _camera(200, 50)])
    rays = rays_from_camera(c2w, INTR, 0.8, 1.8)
    o, d = camera_rays(c2w[1], INTR)
    assert torch.allclose(rays.directions[1], d.reshape(-1, 3), atol=1e-6)
    assert torch.allclose(rays.origins[1], o.reshape(-1, 3))
    assert torch.allclose(rays.directions.norm(dim=-1), torch.ones(2, 24 * 24), atol=1e-6)
    rows = torch.tensor([[0, 5, 23], [7, 7, 12]])
    cols = torch.tensor([[0, 9, 23], [1, 22, 12]])
    sub = rays_from_pixels(c2w, INTR, rows, cols, torch.tensor([0.8, 0.9]), 1.8)
    flat = rows * 24 + cols
    assert torch.allclose(sub.directions, torch.gather(rays.directions, 1, flat[..., None].expand(-1, -1, 3)),
                          atol=1e-6)
    assert torch.equal(sub.near[1], torch.full((3,), 0.9))
    # camera_z_of_directions is the cos(theta) that turns ray distance into z-depth
    pts = rays.points(torch.full((2, 24 * 24, 1), 1.3))[..., 0, :]
    z = world_to_camera(pts, c2w)[..., 2]
    assert torch.allclose(ray_distance_to_z(torch.full_like(z, 1.3), camera_z_of_directions(rays.directions, c2w)),
                          z, atol=1e-5)
    with pytest.raises(ValueError):
        rays_from_camera(c2w, INTR, 1.8, 0.8)


def test_paper_sampling_counts_and_fine_includes_coarse():
    rays = rays_from_camera(_camera(10, 30), INTR, 0.8, 1.8)
    for train in (False, True):
        out = render_rays(SCENE, SCENE, rays, RenderConfig(), train=train, generator=torch.Generator().manual_seed(0))
        assert out.coarse.t.shape == (1, 576, 64) and out.fine.t.shape == (1, 576, 96)
        assert torch.all(out.fine.t[..., 1:] >= out.fine.t[..., :-1])
        assert torch.all(out.fine.t >= 0.8) and torch.all(out.fine.t <= 1.8)
        # pixelNeRF's z_combine: every coarse sample is also a fine sample
        hit = (out.coarse.t[..., :, None] == out.fine.t[..., None, :]).any(-1)
        assert hit.all()
    fine_only = render_rays(SCENE, None, rays, RenderConfig(), train=False)
    assert fine_only.fine is None and fine_only.final is fine_only.coarse


def test_eval_is_deterministic_and_train_is_seeded():
    rays = rays_from_camera(_camera(10, 30), INTR, 0.8, 1.8)
    a = render_rays(SCENE, SCENE, rays, RenderConfig(), train=False)
    b = render_rays(SCENE, SCENE, rays, RenderConfig(), train=False)
    assert torch.equal(a.fine.rgb, b.fine.rgb)
    c = render_rays(SCENE, SCENE, rays, RenderConfig(), train=True, generator=torch.Generator().manual_seed(1))
    d = render_rays(SCENE, SCENE, rays, RenderConfig(), train=True, generator=torch.Generator().manual_seed(1))
    e = render_rays(SCENE, SCENE, rays, RenderConfig(), train=True, generator=torch.Generator().manual_seed(2))
    assert torch.equal(c.fine.t, d.fine.t) and not torch.equal(c.fine.t, e.fine.t)


def test_paper_render_of_analytic_scene_matches_dense_quadrature():
    rays = rays_from_camera(_camera(40, 30), INTR, 0.8, 1.8)
    ref = render_rays(SCENE, None, rays, RenderConfig(sampler=SamplerConfig(n_coarse=4096)), train=False).coarse
    out = render_rays(SCENE, SCENE, rays, RenderConfig(), train=False)
    assert _psnr(out.fine.rgb, ref.rgb) > 45
    assert _psnr(out.fine.rgb, ref.rgb) > _psnr(out.coarse.rgb, ref.rgb)  # the fine pass helps
    assert (ref.opacity > 0.5).float().mean() > 0.2  # the object is in view


@pytest.mark.parametrize("guided", [False, True])
def test_chunked_render_equals_unchunked(guided):
    rays = rays_from_camera(_camera(40, 30), INTR, 0.8, 1.8)
    cfg = RenderConfig(guided=GuidedConfig(enabled=guided))
    guide = None
    if guided:
        src = _camera(0, 20)
        z, mask = SCENE.depth_map(src, INTR, 0.8, 1.8)
        guide = build_depth_guide(src, INTR, z, mask, rays, GuidedConfig())
    full = render_rays(SCENE, SCENE, rays, cfg, train=False, guide=guide)
    chunked = render_image(SCENE, SCENE, rays, cfg, chunk=100, guide=guide)  # 576 = 5 * 100 + 76
    for name in ("rgb", "distance", "opacity", "weights", "t"):
        assert torch.allclose(getattr(chunked.fine, name), getattr(full.fine, name), atol=1e-6), name
        assert torch.allclose(getattr(chunked.coarse, name), getattr(full.coarse, name), atol=1e-6), name


class _TinyField(torch.nn.Module):
    """A learnable field for gradient tests."""

    def __init__(self):
        super().__init__()
        self.lin = torch.nn.Linear(6, 4)

    def forward(self, pts, dirs):
        h = self.lin(torch.cat([pts, dirs[..., None, :].expand_as(pts)], -1))
        return torch.sigmoid(h[..., :3]), torch.nn.functional.softplus(h[..., 3]) + 3.0  # opaque enough that
        # the coarse depth lies inside [near, far] (else the Gaussian samples clamp and carry no gradient)


def test_gradients_reach_both_networks_and_gaussian_centre_flag():
    torch.manual_seed(0)
    coarse, fine = _TinyField(), _TinyField()
    rays = rays_from_camera(_camera(10, 30), INTR, 0.8, 1.8).slice(0, 50)
    for detach in (False, True):
        coarse.zero_grad()
        cfg = RenderConfig(sampler=SamplerConfig(n_importance=0, detach_gaussian_center=detach))
        out = render_rays(coarse, fine, rays, cfg, train=True, generator=torch.Generator().manual_seed(0))
        out.fine.rgb.sum().backward()  # fine loss only
        reached = coarse.lin.weight.grad is not None and coarse.lin.weight.grad.abs().sum() > 0
        assert reached != detach  # pixelNeRF: the fine loss reaches the coarse net through the Gaussian centre
        assert fine.lin.weight.grad.abs().sum() > 0


def test_field_shape_and_guide_flag_errors():
    rays = rays_from_camera(_camera(10, 30), INTR, 0.8, 1.8)
    with pytest.raises(ValueError, match="field returned"):
        evaluate_field(lambda p, d: (p[..., :2], p[..., 0]), rays, torch.ones(1, 576, 3))
    with pytest.raises(ValueError, match="DepthGuide"):
        render_rays(SCENE, SCENE, rays, RenderConfig(guided=GuidedConfig(enabled=True)), train=False)
    with pytest.raises(ValueError, match="chunk"):
        render_image(SCENE, SCENE, rays, RenderConfig(), chunk=0)
    assert isinstance(rays, RayBundle)


def test_pre_drawn_draws_are_the_samplers_own_draws_in_order():
    """``draw_paper`` makes the draws a random render makes, in the documented order, from the same generator(s):
    against torch's own draws by hand; with one generator per row, row ``b`` is generator ``b``'s."""
    cfg = RenderConfig(sampler=SamplerConfig(n_coarse=6, n_importance=3, n_gaussian=2), sigma_noise_std=0.5)
    d = draw_paper((2, 5), cfg, fine=True, sigma_noise=True, generator=torch.Generator().manual_seed(4))
    g = torch.Generator().manual_seed(4)
    expected = [torch.rand(2, 5, 6, generator=g), torch.randn(2, 5, 6, generator=g), torch.rand(2, 5, 3, generator=g),
                torch.randn(2, 5, 2, generator=g), torch.randn(2, 5, 11, generator=g)]
    got = [d.coarse_jitter, d.coarse_sigma, d.importance, d.gaussian, d.fine_sigma]
    assert all(torch.equal(a, b) for a, b in zip(got, expected, strict=True))
    rows = draw_paper((2, 5), cfg, fine=True, sigma_noise=True,
                      generator=[torch.Generator().manual_seed(7), torch.Generator().manual_seed(8)])
    for b, seed in enumerate((7, 8)):
        alone = draw_paper((1, 5), cfg, fine=True, sigma_noise=True, generator=torch.Generator().manual_seed(seed))
        assert torch.equal(rows.gaussian[b], alone.gaussian[0]) and torch.equal(rows.fine_sigma[b], alone.fine_sigma[0])
    no_noise = draw_paper((2, 5), cfg, fine=False, sigma_noise=False, generator=None)
    assert no_noise.coarse_sigma is None and no_noise.importance is None and no_noise.fine_sigma is None


def test_a_render_given_its_draws_equals_one_that_draws_them():
    """Training renders (density noise on): drawing up front changes nothing, bit for bit; the draws must not
    come with a generator or a guide."""
    rays = rays_from_camera(_camera(40, 25), INTR, 0.8, 1.8).slice(0, 50)
    cfg = RenderConfig(sigma_noise_std=0.3)
    own = render_rays(SCENE, SCENE, rays, cfg, train=True, generator=torch.Generator().manual_seed(2))
    draws = draw_paper((1, 50), cfg, fine=True, sigma_noise=True, generator=torch.Generator().manual_seed(2))
    given = render_rays(SCENE, SCENE, rays, cfg, train=True, draws=draws)
    for a, b in ((own.coarse, given.coarse), (own.fine, given.fine)):
        assert torch.equal(a.t, b.t) and torch.equal(a.rgb, b.rgb) and torch.equal(a.weights, b.weights)
    other = render_rays(SCENE, SCENE, rays, cfg, train=True,
                        draws=draw_paper((1, 50), cfg, fine=True, sigma_noise=True,
                                         generator=torch.Generator().manual_seed(3)))
    assert not torch.equal(other.fine.t, own.fine.t)
    with pytest.raises(ValueError, match="pre-drawn"):
        render_rays(SCENE, SCENE, rays, cfg, train=True, draws=draws, generator=torch.Generator())


def test_ray_directions_match_a_per_pixel_loop_with_an_off_centre_principal_point():
    """Non-square image, ``cx != cy``: pixel (i, j) looks along ``R ((j - cx) / f, (i - cy) / f, 1)``, normalised,
    and is ray ``i * W + j``."""
    intr = Intrinsics(focal=20.0, cx=6.3, cy=2.9, height=5, width=9)
    c2w = torch.cat([_camera(30, 20), _camera(200, 50)]).double()
    rays = rays_from_camera(c2w, intr, 0.8, 1.8)
    rows = torch.tensor([[0, 4, 2, 3], [1, 0, 4, 2]])
    cols = torch.tensor([[0, 8, 5, 1], [7, 3, 0, 6]])
    sub = rays_from_pixels(c2w, intr, rows, cols, 0.8, 1.8)
    for b in range(2):
        for i in range(intr.height):
            for j in range(intr.width):
                d = torch.tensor([(j - intr.cx) / intr.focal, (i - intr.cy) / intr.focal, 1.0], dtype=torch.float64)
                expect = c2w[b, :3, :3] @ (d / d.norm())
                assert torch.allclose(rays.directions[b, i * intr.width + j], expect, atol=1e-12)
                assert torch.equal(rays.origins[b, i * intr.width + j], c2w[b, :3, 3])
        for k in range(rows.shape[1]):
            i, j = int(rows[b, k]), int(cols[b, k])
            assert torch.allclose(sub.directions[b, k], rays.directions[b, i * intr.width + j], atol=1e-12)


def test_ray_bounds_must_have_positive_length():
    c2w = _camera(30, 20)
    for near, far in ((1.0, 1.0), (1.8, 0.8), (torch.tensor([1.2]), 1.2)):
        with pytest.raises(ValueError, match="far > near"):
            rays_from_camera(c2w, INTR, near, far)
    rays_from_camera(c2w, INTR, 1.0, 1.0 + 1e-4)  # any positive length is accepted


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_analytic_scene_hits_and_renders_on_cuda():
    """The analytic scene builds its constants on the rays' device: the same hits and render as on the CPU."""
    rays = rays_from_camera(_camera(40, 30), INTR, 0.8, 1.8)
    dist, hit = SCENE.ray_hits(rays)
    cuda_rays = rays.to("cuda")
    dist_c, hit_c = SCENE.ray_hits(cuda_rays)
    assert torch.equal(hit_c.cpu(), hit)
    torch.testing.assert_close(dist_c.cpu()[hit], dist[hit], rtol=1e-5, atol=1e-6)
    out = render_rays(SCENE, SCENE, cuda_rays, RenderConfig(), train=False)
    ref = render_rays(SCENE, SCENE, rays, RenderConfig(), train=False)
    torch.testing.assert_close(out.fine.rgb.cpu(), ref.fine.rgb, rtol=1e-4, atol=1e-4)
