"""Disparity convention, normalisation invariance, and the affine-invariant depth metrics."""

from __future__ import annotations

import pytest
import torch

from depthnerf.depth.estimators import OracleEstimator, make_estimator, oracle_disparity
from depthnerf.depth.metrics import affine_invariant_scores, align_disparity
from depthnerf.depth.normalize import BACKGROUND_VALUE, FOREGROUND_CLAMP, normalize_disparity
from depthnerf.errors import DepthnerfError


def _scene(batch: int = 3, size: int = 24, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Random smooth z-depth maps on a disc foreground (0 = background)."""
    gen = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, size), torch.linspace(-1, 1, size), indexing="ij")
    mask = (xx**2 + yy**2 < 0.6).expand(batch, size, size)
    coef = torch.rand(batch, 3, generator=gen)
    depth = 1.2 + 0.3 * coef[:, :1, None] * xx + 0.2 * coef[:, 1:2, None] * yy + 0.1 * coef[:, 2:, None] * xx * yy
    return torch.where(mask, depth, torch.zeros_like(depth)), mask


def test_oracle_is_inverse_z_on_foreground_and_zero_on_background():
    depth, mask = _scene()
    disp = oracle_disparity(depth)
    assert torch.allclose(disp[mask], 1.0 / depth[mask])
    assert (disp[~mask] == 0).all()
    # larger disparity = closer: the nearest foreground pixel has the largest disparity
    flat_d, flat_z = disp[0][mask[0]], depth[0][mask[0]]
    assert flat_d.argmax() == flat_z.argmin()
    images = torch.rand(depth.shape[0], 3, *depth.shape[1:])
    est = make_estimator("oracle")
    assert isinstance(est, OracleEstimator) and est.needs_depth
    assert torch.equal(est.predict(images, depth), disp)
    with pytest.raises(DepthnerfError, match="ground-truth depth"):
        est.predict(images)
    assert make_estimator("none") is None


@pytest.mark.parametrize(("scale", "shift"), [(1.0, 0.0), (3.7, -2.0), (0.01, 5.0), (250.0, 1e3)])
def test_normalisation_is_invariant_to_positive_affine_maps(scale, shift):
    depth, mask = _scene(seed=1)
    disp = oracle_disparity(depth) + 0.05 * torch.randn(depth.shape, generator=torch.Generator().manual_seed(2))
    ref = normalize_disparity(disp, mask)
    out = normalize_disparity(scale * disp + shift, mask)
    assert torch.allclose(out, ref, atol=2e-3 if scale * 1e-3 < abs(shift) else 1e-4)
    assert (out[~mask] == BACKGROUND_VALUE).all()


def test_normalisation_statistics_match_a_reference_loop():
    depth, mask = _scene(batch=2, seed=3)
    disp = oracle_disparity(depth) * 10 + torch.randn(depth.shape, generator=torch.Generator().manual_seed(4))
    out = normalize_disparity(disp, mask)
    for b in range(2):
        values = sorted(disp[b][mask[b]].tolist())
        median = values[(len(values) - 1) // 2]  # lower median
        mad = sum(abs(v - median) for v in values) / len(values)
        expect = ((disp[b] - median) / mad).clamp(-FOREGROUND_CLAMP, FOREGROUND_CLAMP)
        assert torch.allclose(out[b][mask[b]], expect[mask[b]], atol=1e-5)
    # larger disparity stays larger (monotone) and the output is bounded
    assert out.min() >= BACKGROUND_VALUE and out.max() <= FOREGROUND_CLAMP


def test_normalisation_of_empty_and_constant_masks_is_finite():
    disp = torch.rand(2, 8, 8)
    empty = torch.zeros(2, 8, 8, dtype=torch.bool)
    out = normalize_disparity(disp, empty)
    assert torch.isfinite(out).all() and (out == BACKGROUND_VALUE).all()
    const = normalize_disparity(torch.full((8, 8), 3.0), torch.ones(8, 8, dtype=torch.bool))
    assert torch.isfinite(const).all() and (const == 0).all()
    batched = normalize_disparity(torch.rand(2, 3, 8, 8), torch.rand(2, 3, 8, 8) > 0.5)
    assert batched.shape == (2, 3, 8, 8)


def test_metric_affine_prediction_gives_zero_error():
    depth, mask = _scene(seed=5)
    pred = 4.2 * oracle_disparity(depth) - 0.7  # an affine map of the true disparity (background is ignored)
    pred = torch.where(mask, pred, torch.randn_like(pred))
    scores = affine_invariant_scores(pred, depth)
    assert scores.valid.all()
    assert torch.allclose(scores.abs_rel, torch.zeros(3), atol=1e-5)
    assert torch.equal(scores.delta1, torch.ones(3))


def test_metric_closed_form_scaled_depth_and_alignment():
    # aligned disparity = target exactly when the target is itself affine in the prediction
    pred = torch.rand(2, 5, 5)
    target = 2 * pred + 1
    ok = torch.ones_like(pred, dtype=torch.bool)
    assert torch.allclose(align_disparity(pred, target, ok), target, atol=1e-5)
    # a constant prediction aligns to the mean disparity: depth = 1 / mean(1/z); check AbsRel by brute force
    depth = torch.tensor([[[1.0, 2.0], [4.0, 0.0]]])
    scores = affine_invariant_scores(torch.ones(1, 2, 2), depth)
    z_hat = 1 / ((1 + 0.5 + 0.25) / 3)
    gts = [1.0, 2.0, 4.0]
    expect_rel = sum(abs(z_hat - z) / z for z in gts) / 3
    expect_d1 = sum(max(z_hat / z, z / z_hat) < 1.25 for z in gts) / 3
    assert scores.abs_rel.item() == pytest.approx(expect_rel, rel=1e-5)
    assert scores.delta1.item() == pytest.approx(expect_d1)
    assert not affine_invariant_scores(torch.ones(1, 2, 2), torch.zeros(1, 2, 2)).valid.any()
