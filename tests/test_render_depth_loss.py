"""Closed-form scale/shift fit and the scale-and-shift-invariant depth loss."""

import pytest
import torch

from depthnerf.render.depth_guide import align_disparity_to_depth
from depthnerf.render.depth_loss import fit_scale_shift, ssi_depth_loss


def _data(seed=0, b=3, r=200):
    g = torch.Generator().manual_seed(seed)
    depth = 0.9 + 0.6 * torch.rand(b, r, generator=g)
    mask = torch.rand(b, r, generator=g) > 0.3
    return g, depth, mask


def test_fit_scale_shift_recovers_affine_and_ignores_masked_garbage():
    g, x, mask = _data()
    y = 2.5 * x - 0.7
    y = torch.where(mask, y, torch.full_like(y, float("nan")))  # masked-out entries may be anything
    s, b = fit_scale_shift(torch.where(mask, x, torch.full_like(x, float("inf"))), y, mask)
    assert torch.allclose(s, torch.full_like(s, 2.5), atol=1e-4) and torch.allclose(b, torch.full_like(b, -0.7),
                                                                                    atol=1e-4)
    s0, b0 = fit_scale_shift(torch.ones(1, 5), torch.arange(5.0)[None], torch.ones(1, 5, dtype=torch.bool))
    assert s0.item() == 0 and b0.item() == pytest.approx(2.0)  # constant x: mean of y


def test_ssi_loss_zero_for_affine_prior_and_invariant_to_prior_scale_shift():
    g, depth, mask = _data(1)
    disp = 1 / depth
    assert ssi_depth_loss(depth, 3.0 * disp + 0.2, mask).item() < 1e-10
    assert ssi_depth_loss(depth, -0.5 * disp + 4.0, mask).item() < 1e-10
    prior = disp + 0.05 * torch.randn(depth.shape, generator=g)  # not affine: positive loss
    base = ssi_depth_loss(depth, prior, mask)
    assert base.item() > 1e-4
    for a, c in ((7.0, -3.0), (0.1, 3.0), (-2.0, 0.5)):
        assert ssi_depth_loss(depth, a * prior + c, mask).item() == pytest.approx(base.item(), rel=1e-4)
    # background rays do not matter
    noisy_bg = torch.where(mask, prior, torch.randn(depth.shape, generator=g) * 100)
    assert ssi_depth_loss(depth, noisy_bg, mask).item() == pytest.approx(base.item(), rel=1e-6)


def test_ssi_loss_converts_ray_distance_to_z():
    g, z, mask = _data(2)
    cos = 0.85 + 0.15 * torch.rand(z.shape, generator=g)
    t = z / cos
    prior = 2.0 / z + 1.0
    assert ssi_depth_loss(t, prior, mask, dirs_cam_z=cos).item() < 1e-10
    assert ssi_depth_loss(t, prior, mask).item() > 1e-5  # treating t as z is wrong


def test_ssi_gradient_equals_detached_fit_gradient_and_is_orthogonal_to_prior():
    g, depth, mask = _data(3, b=1)
    prior = 1 / depth + 0.05 * torch.randn(depth.shape, generator=g)
    d1 = depth.clone().requires_grad_(True)
    ssi_depth_loss(d1, prior, mask).backward()
    d2 = depth.clone().requires_grad_(True)
    disp = 1 / d2
    with torch.no_grad():
        s, b = fit_scale_shift(prior, disp, mask)
    res = torch.where(mask, disp - (s[:, None] * prior + b[:, None]), torch.zeros_like(disp))
    ((res ** 2).sum() / mask.sum()).backward()
    assert torch.allclose(d1.grad, d2.grad, rtol=1e-4, atol=1e-8)
    # dL/d(disp) is the residual: orthogonal to the prior and to constants on the mask
    grad_disp = d1.grad * -(depth ** 2)
    m = mask.to(grad_disp.dtype)
    assert abs((grad_disp * m).sum().item()) < 1e-4 * grad_disp.abs().sum().item()
    assert abs((grad_disp * prior * m).sum().item()) < 1e-4 * (grad_disp * prior).abs().sum().item()


def test_ssi_loss_skips_images_without_enough_foreground():
    g, depth, mask = _data(4, b=2)
    prior = 1 / depth + 0.05 * torch.randn(depth.shape, generator=g)
    only_first = ssi_depth_loss(depth[:1], prior[:1], mask[:1])
    mask2 = mask.clone()
    mask2[1] = False
    mask2[1, :2] = True  # 2 < MIN_PIXELS
    assert ssi_depth_loss(depth, prior, mask2).item() == pytest.approx(only_first.item())
    none = ssi_depth_loss(depth.requires_grad_(True), prior, torch.zeros_like(mask))
    assert none.item() == 0 and none.requires_grad


def test_align_disparity_to_depth_recovers_metric_depth():
    g = torch.Generator().manual_seed(5)
    z = 1.0 + 0.5 * torch.rand(2, 16, 16, generator=g)
    mask = torch.rand(2, 16, 16, generator=g) > 0.4
    disp = torch.stack([4.0 / z[0] + 0.3, 0.2 / z[1] - 5.0])  # any positive scale, any shift
    ref = torch.where(mask, z, torch.zeros_like(z))  # the reference only exists on the mask
    out = align_disparity_to_depth(disp, ref, mask)
    assert torch.allclose(out, z, rtol=1e-4)  # the fit extends to every pixel
    assert torch.all(align_disparity_to_depth(disp, ref, torch.zeros_like(mask)) == 0)


def test_ssi_loss_leaves_out_rays_fainter_than_min_opacity():
    """An empty foreground ray (opacity 0, normalised depth 0, so disparity 1 / min_depth) skews the fit for every
    other ray; with the render's opacity passed, the loss is exactly the loss without that ray, and its gradient
    on the other rays is theirs alone."""
    g, depth, mask = _data(3, b=1, r=64)
    mask[:] = True
    prior = 1 / depth + 0.02 * torch.randn(depth.shape, generator=g)
    opacity = torch.full_like(depth, 0.9)
    depth_with_hole, opacity[0, 5] = depth.clone(), 0.0
    depth_with_hole[0, 5] = 0.0  # what normalized_distance gives an empty ray
    keep = torch.ones_like(mask)
    keep[0, 5] = False
    clean = ssi_depth_loss(depth[keep][None], prior[keep][None], mask[keep][None])
    skewed = ssi_depth_loss(depth_with_hole, prior, mask)
    assert skewed.item() > 1e3 * clean.item()  # the outlier: what happens without the opacity
    d = depth_with_hole.clone().requires_grad_(True)
    guarded = ssi_depth_loss(d, prior, mask, opacity=opacity, min_opacity=0.5)
    assert guarded.item() == pytest.approx(clean.item(), rel=1e-6)
    guarded.backward()
    d_ref = depth[keep][None].clone().requires_grad_(True)
    ssi_depth_loss(d_ref, prior[keep][None], mask[keep][None]).backward()
    assert d.grad[0, 5].item() == 0.0
    torch.testing.assert_close(d.grad[keep][None], d_ref.grad, rtol=1e-5, atol=1e-12)
    # the threshold is inclusive, and the opacity never carries gradient
    opacity = torch.full_like(depth, 0.9)
    o = opacity.clone().requires_grad_(True)
    ssi_depth_loss(depth.clone().requires_grad_(True), prior, mask, opacity=o, min_opacity=0.9).backward()
    assert o.grad is None
    assert ssi_depth_loss(depth, prior, mask, opacity=opacity, min_opacity=0.9).item() == pytest.approx(
        ssi_depth_loss(depth, prior, mask).item(), rel=1e-6)

