"""The depth guide and the guided sampler against hand-computed cases: the guesses of rays along known geometry,
the sampling window, the alignment's pixel minimum, and each ray group's sample counts, bounds and networks."""

from __future__ import annotations

import pytest
import torch

from depthnerf.data.cameras import Intrinsics
from depthnerf.render.config import GuidedConfig, RenderConfig, SamplerConfig
from depthnerf.render.depth_guide import DepthGuide, align_disparity_to_depth, build_depth_guide
from depthnerf.render.pipeline import render_rays
from depthnerf.render.rays import RayBundle


def test_window_of_each_ray_class_by_hand():
    """Rays (near 1, far 3): a trusted guess whose window is ``t_guess +- spread``; a trusted guess after an earlier
    entry (``t_enter`` < ``t_guess - spread``: the window starts at the entry); an untrusted occupied ray
    ``[t_enter, far]``; a trusted guess near both ends, clipped to ``[near, far]``."""
    t_guess = torch.tensor([[2.0, 2.5, 1.6, 1.02, 2.95]])
    t_enter = torch.tensor([[1.95, 1.4, 1.6, 1.0, 2.9]])
    valid = torch.tensor([[True, True, False, True, True]])
    guide = DepthGuide(t_guess=t_guess, t_enter=t_enter, valid=valid, occupied=torch.ones(1, 5, dtype=torch.bool),
                       spread=torch.full((1, 5), 0.1))
    lo, hi = guide.window(torch.ones(1, 5), torch.full((1, 5), 3.0))
    assert torch.allclose(lo, torch.tensor([[1.9, 1.4, 1.6, 1.0, 2.85]]))
    assert torch.allclose(hi, torch.tensor([[2.1, 2.6, 3.0, 1.12, 3.0]]))


def test_alignment_needs_two_pixels_and_recovers_an_affine_disparity():
    """``disp = 2 / z - 0.3`` on two reference pixels is recovered exactly (``z = 2 / (disp + 0.3)``) on every
    pixel, even one outside the mask; a single reference pixel fits nothing (all 0), nor does an aligned disparity
    at or below ``min_disparity`` (the last pixel, ``disp = -0.3``)."""
    z = torch.tensor([[[1.0, 2.0, 4.0, 0.0]]], dtype=torch.float64)
    disp = torch.tensor([[[2.0 - 0.3, 1.0 - 0.3, 0.5 - 0.3, -0.3]]], dtype=torch.float64)
    two = torch.tensor([[[True, True, False, False]]])
    aligned = align_disparity_to_depth(disp, z, two)
    assert torch.allclose(aligned, torch.tensor([[[1.0, 2.0, 4.0, 0.0]]], dtype=torch.float64), atol=1e-9)
    one = torch.tensor([[[True, False, False, False]]])
    assert torch.equal(align_disparity_to_depth(disp, z, one), torch.zeros_like(z))


def test_guesses_of_rays_from_the_source_camera_read_their_own_pixel():
    """Target rays from the source camera's centre (identity pose) through ``(u, v) = (j - 0.4, i - 0.4)`` of a
    3 x 5 image: every march point projects there, the nearest pixel is ``(i, j)`` (edges included), so each ray
    crosses its own pixel's depth ``z_ij = 2 + 0.1 j + 0.05 i`` at ray distance ``z_ij / d_z`` (``d`` unit), and the
    crossing is the exact zero of the linear ``diff`` along the ray."""
    intr = Intrinsics(focal=4.0, cx=2.0, cy=1.0, height=3, width=5)
    ii, jj = torch.meshgrid(torch.arange(3.0, dtype=torch.float64), torch.arange(5.0, dtype=torch.float64),
                            indexing="ij")
    z = (2 + 0.1 * jj + 0.05 * ii)[None]
    dirs = torch.stack([(jj - 0.4 - intr.cx) / intr.focal, (ii - 0.4 - intr.cy) / intr.focal,
                        torch.ones_like(ii)], dim=-1).reshape(1, 15, 3)
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    rays = RayBundle(torch.zeros_like(dirs), dirs, torch.full((1, 15), 1.0, dtype=torch.float64),
                     torch.full((1, 15), 4.0, dtype=torch.float64))
    eye = torch.eye(4, dtype=torch.float64)[None]
    guide = build_depth_guide(eye, intr, z, torch.ones_like(z, dtype=torch.bool), rays, GuidedConfig())
    assert guide.valid.all() and guide.occupied.all()
    assert torch.allclose(guide.t_guess, z.reshape(1, 15) / dirs[..., 2], atol=1e-9)


@pytest.mark.parametrize(
    ("steps", "z", "valid", "occupied", "t_guess", "t_enter"),
    [
        # 100 steps, points t_k = 1.015 + 0.03 k: diff 0.007 at t_20 = 1.615, -0.023 at t_21: a trusted crossing
        # at the zero of diff, z itself (not the midpoint 1.63); first point within spread 0.1: t_17 = 1.525
        (100, 1.622, True, True, 1.622, 1.525),
        # 50 steps, t_k = 1.03 + 0.06 k: diff 0.05 at t_10 = 1.63 (beyond the tolerance 0.03), -0.01 at t_11
        (50, 1.68, False, True, 1.63, 1.63),
        # 4 steps, t = 1.375, 2.125, ...: diff 0.005, then -0.745 (far behind): a shadow entry, not a crossing
        (4, 1.38, False, True, 1.375, 1.375),
        # a mask pixel without depth is no surface: the ray is empty
        (100, 0.0, False, False, 0.0, 0.0),
    ],
)
def test_one_ray_along_the_axis_against_a_march_by_hand(steps, z, valid, occupied, t_guess, t_enter):
    """The source camera's own optical axis (1 x 1 image, depth ``z``), t in [1, 4], spread 0.1, tolerance 0.03."""
    intr = Intrinsics(focal=1.0, cx=0.0, cy=0.0, height=1, width=1)
    dirs = torch.tensor([[[0.0, 0.0, 1.0]]], dtype=torch.float64)
    rays = RayBundle(torch.zeros_like(dirs), dirs, torch.ones(1, 1, dtype=torch.float64),
                     torch.full((1, 1), 4.0, dtype=torch.float64))
    cfg = GuidedConfig(march_steps=steps, spread=0.1, surface_tolerance=0.03, mask_dilation=0)
    guide = build_depth_guide(torch.eye(4, dtype=torch.float64)[None], intr,
                              torch.full((1, 1, 1), z, dtype=torch.float64), torch.ones(1, 1, 1, dtype=torch.bool),
                              rays, cfg)
    assert (guide.valid.item(), guide.occupied.item()) == (valid, occupied)
    assert guide.t_guess.item() == pytest.approx(t_guess, abs=1e-9)
    assert guide.t_enter.item() == pytest.approx(t_enter, abs=1e-9)
    if occupied:  # the window: t_guess +- spread (from t_enter when earlier) on a crossing, else [t_enter, far]
        lo, hi = guide.window(rays.near, rays.far)
        expect = (min(t_enter, t_guess - 0.1), t_guess + 0.1) if valid else (t_enter, 4.0)
        assert (lo.item(), hi.item()) == pytest.approx(expect, abs=1e-9)


class _Counted:
    """A grey slab of density 5 on 1.25 < z < 1.35, counting the points it is asked about."""

    def __init__(self):
        self.points = 0

    def __call__(self, pts, dirs):
        self.points += pts.shape[:-1].numel()
        sigma = torch.where((pts[..., 2] - 1.3).abs() < 0.05, 5.0, 0.0).to(pts.dtype)
        return torch.full((*pts.shape[:-1], 3), 0.5, dtype=pts.dtype), sigma


def test_each_ray_group_gets_its_counts_its_own_bounds_and_its_networks():
    """Four rays along +z, near 0.8, far 1.8 ... 2.1, occupied and empty in turn (default counts: occupied 8 + 16
    then 16 + 8, empty 16 then 8). First pass "fine": only the fine network runs, 48 and 24 points per ray;
    "coarse": the coarse network runs pass 1 (24 and 16) and the fine one the whole union. An empty ray's pass 1
    is the 16 bin midpoints of its own [near, far], padded with its far."""
    fars = torch.tensor([[1.8, 1.9, 2.0, 2.1]], dtype=torch.float64)
    dirs = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(1, 4, 3)
    rays = RayBundle(torch.zeros_like(dirs), dirs, torch.full((1, 4), 0.8, dtype=torch.float64), fars)
    occupied = torch.tensor([[True, False, True, False]])
    guide = DepthGuide(t_guess=torch.full((1, 4), 1.3, dtype=torch.float64),
                       t_enter=torch.full((1, 4), 1.2, dtype=torch.float64), valid=occupied, occupied=occupied,
                       spread=torch.full((1, 4), 0.1, dtype=torch.float64))
    for first_pass, coarse_points in (("fine", 0), ("coarse", 2 * 24 + 2 * 16)):
        coarse, fine = _Counted(), _Counted()
        cfg = RenderConfig(guided=GuidedConfig(enabled=True, first_pass=first_pass))
        out = render_rays(coarse, fine, rays, cfg, train=False, guide=guide)
        assert (coarse.points, fine.points) == (coarse_points, 2 * 48 + 2 * 24), first_pass
        for r in (1, 3):
            far = fars[0, r].item()
            mids = [0.8 + (k + 0.5) * (far - 0.8) / 16 for k in range(16)]
            assert out.coarse.t[0, r].tolist() == pytest.approx(mids + [far] * 8, abs=1e-12)
        assert (out.fine.t <= fars[..., None]).all() and (out.fine.t >= 0.8).all()
        assert (out.fine.t[0, 1] < fars[0, 1]).sum() == 24 and (out.fine.t[0, 0] < fars[0, 0]).sum() == 48


def test_empty_rays_are_drawn_at_random_when_evaluation_asks_for_it():
    """With ``eval_random`` every empty ray's 16 pass-1 samples are one random point in each bin of [near, far]
    (then the padding, at far), other points for another seed."""
    dirs = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(1, 2, 3)
    rays = RayBundle(torch.zeros_like(dirs), dirs, torch.full((1, 2), 0.8, dtype=torch.float64),
                     torch.full((1, 2), 1.8, dtype=torch.float64))
    none = torch.zeros(1, 2, dtype=torch.bool)
    zeros = torch.zeros(1, 2, dtype=torch.float64)
    guide = DepthGuide(t_guess=zeros, t_enter=zeros, valid=none, occupied=none, spread=zeros + 0.1)
    cfg = RenderConfig(sampler=SamplerConfig(eval_random=True), guided=GuidedConfig(enabled=True))
    draws = [render_rays(_Counted(), _Counted(), rays, cfg, train=False, guide=guide,
                         generator=torch.Generator().manual_seed(seed)).coarse.t[0] for seed in (0, 1)]
    lo = 0.8 + torch.arange(16, dtype=torch.float64) / 16
    for t in draws:
        assert ((t[:, :16] >= lo) & (t[:, :16] <= lo + 1 / 16)).all() and (t[:, 16:] == 1.8).all()
    assert not torch.equal(draws[0], draws[1])
