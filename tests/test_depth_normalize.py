"""Disparity convention, normalisation invariance, and the affine-invariant depth metrics."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from depthnerf.depth.estimators import OracleEstimator, make_estimator, oracle_disparity
from depthnerf.depth.metrics import affine_invariant_scores, align_disparity, fit_scale_shift
from depthnerf.depth.normalize import (
    BACKGROUND_VALUE,
    FOREGROUND_CLAMP,
    SCALE_FLOOR,
    foreground_median_and_deviation,
    normalize_disparity,
)
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


def _reference_normalize(values: list[float]) -> tuple[float, float]:
    """Lower median and mean absolute deviation around it, by sorting (the module docstring's definitions)."""
    values = sorted(values)
    median = values[(len(values) - 1) // 2]
    return median, sum(abs(v - median) for v in values) / len(values)


def test_normalisation_clamps_both_ends_and_skips_non_finite_foreground():
    """An outlier far below the median is clamped to -FOREGROUND_CLAMP (one far above to +FOREGROUND_CLAMP);
    NaN and inf foreground pixels are left out of the statistics and get the background value."""
    gen = torch.Generator().manual_seed(6)
    disp = 1.0 + 0.1 * torch.rand(6, 6, generator=gen, dtype=torch.float64)
    disp[0, 0], disp[0, 1] = -100.0, 100.0
    disp[1, 1], disp[2, 2] = float("nan"), float("inf")
    mask = torch.ones(6, 6, dtype=torch.bool)
    mask[5] = False
    out = normalize_disparity(disp, mask)
    finite = mask & torch.isfinite(disp)
    median, mad = _reference_normalize(disp[finite].tolist())
    expect = ((disp - median) / mad).clamp(-FOREGROUND_CLAMP, FOREGROUND_CLAMP)
    assert torch.allclose(out[finite].double(), expect[finite], atol=1e-5)
    assert (out[0, 0], out[0, 1]) == (-FOREGROUND_CLAMP, FOREGROUND_CLAMP)
    assert (out[~finite] == BACKGROUND_VALUE).all() and torch.isfinite(out).all()


def test_normalisation_is_exact_for_tiny_disparity_scales():
    """Invariance holds at any scale whose deviation is above the floor: 3e-5 * d (deviation ~100 floors)
    normalises like d, with no floor-sized term entering the division."""
    depth, mask = _scene(batch=2, seed=7)
    disp = oracle_disparity(depth).double()
    ref = normalize_disparity(disp, mask)
    for scale in (1e-2, 3e-5):
        _, mad = _reference_normalize((scale * disp[0][mask[0]]).tolist())
        assert mad > 100 * SCALE_FLOOR
        assert torch.allclose(normalize_disparity(scale * disp, mask), ref, atol=1e-4)


def test_foreground_statistics_of_rows_without_foreground_are_zero():
    disp = torch.tensor([[3.0, 1.0, 2.0, 7.0], [5.0, 6.0, 7.0, 8.0]])
    mask = torch.tensor([[True, True, True, False], [False, False, False, False]])
    median, dev, count = foreground_median_and_deviation(disp, mask)
    assert median.tolist() == [2.0, 0.0] and dev.tolist() == [pytest.approx(2 / 3), 0.0] and count.tolist() == [3, 0]


def _reference_scores(pred: torch.Tensor, gt: torch.Tensor) -> tuple[list[float], list[float], float]:
    """Per-image AbsRel and delta1 by numpy least squares on the foreground, the cap at 10 x max depth, and the
    smallest aligned disparity seen (to show the cap was needed)."""
    rel, d1, lowest = [], [], float("inf")
    for p, z in zip(pred.double().numpy(), gt.double().numpy(), strict=True):
        keep = (z > 0) & np.isfinite(p)
        a, b = np.linalg.lstsq(np.stack([p[keep], np.ones(keep.sum())], axis=1), 1 / z[keep], rcond=None)[0]
        aligned = a * p[keep] + b
        lowest = min(lowest, aligned.min())
        z_hat = 1 / np.maximum(aligned, 1 / (10 * z.max()))
        rel.append(float(np.mean(np.abs(z_hat - z[keep]) / z[keep])))
        d1.append(float(np.mean(np.maximum(z_hat / z[keep], z[keep] / z_hat) < 1.25)))
    return rel, d1, lowest


def test_metric_matches_a_numpy_reference_with_outliers_and_non_finite_predictions():
    """Depth 1..4 across the image (two background rows). Image 0: exact disparity but one outlier whose aligned
    disparity is negative (its depth is capped at 10 x max z); image 1: noisy, with NaN and inf on the foreground
    (not scored)."""
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, 16), torch.linspace(-1, 1, 16), indexing="ij")
    depth = (2.5 + 1.5 * xx).double().expand(2, 16, 16).clone()
    depth[:, :2] = 0.0
    noise = 0.05 * torch.randn(16, 16, generator=torch.Generator().manual_seed(9), dtype=torch.float64)
    pred = torch.stack([1 / depth[0].clamp_min(0.5), 1 / depth[1].clamp_min(0.5) + noise])
    pred[0, 8, 8] = -1.0
    pred[1, 10, 11], pred[1, 11, 10] = float("nan"), float("inf")
    rel, d1, lowest = _reference_scores(pred, depth)
    assert lowest < 0
    scores = affine_invariant_scores(pred, depth)
    assert scores.valid.all()
    assert scores.abs_rel.tolist() == pytest.approx(rel, rel=1e-5)
    assert scores.delta1.tolist() == pytest.approx(d1, abs=1e-7)


def test_delta_threshold_is_strict_and_constant_predictions_get_no_scale():
    """A constant prediction aligns to the mean disparity: z in {2.5, 5/3} gives mean 1/z = 0.5 (exact in
    binary), predicted depth 2, ratios 1.25 (not < 1.25: a miss) and 1.2 (a hit)."""
    scores = affine_invariant_scores(torch.ones(1, 1, 2, dtype=torch.float64),
                                     torch.tensor([[[2.5, 1 / 0.6]]], dtype=torch.float64))
    assert scores.delta1.item() == 0.5 and scores.abs_rel.item() == pytest.approx(0.2)
    # 0.1 is not a binary fraction: its row mean carries rounding, which must not turn into a slope
    x = torch.full((2, 9), 0.1, dtype=torch.float64)
    y = torch.arange(18, dtype=torch.float64).reshape(2, 9) ** 2
    s, b = fit_scale_shift(x, y, torch.ones(2, 9, dtype=torch.bool))
    assert s.tolist() == [0.0, 0.0] and torch.allclose(b, y.mean(-1))


def test_rows_and_images_without_foreground_get_zeros_not_nan():
    """fit_scale_shift: an empty row is ``s = b = 0`` (its docstring), whatever the masked-out entries hold; the
    scores of an image without foreground are 0 and flagged invalid, beside a scored image."""
    x = torch.tensor([[1.0, 2.0, 3.0], [float("nan"), 5.0, float("inf")]])
    y = torch.tensor([[3.0, 5.0, 7.0], [1.0, float("inf"), 2.0]])
    s, b = fit_scale_shift(x, y, torch.tensor([[True, True, True], [False, False, False]]))
    assert s.tolist() == [pytest.approx(2.0), 0.0] and b.tolist() == [pytest.approx(1.0), 0.0]
    depth = torch.stack([torch.full((4, 4), 2.0), torch.zeros(4, 4)]).double()
    scores = affine_invariant_scores(torch.rand(2, 4, 4, dtype=torch.float64), depth)
    assert scores.valid.tolist() == [True, False]
    assert scores.abs_rel.tolist() == [0.0, 0.0] and scores.delta1.tolist() == [1.0, 0.0]


def test_background_pixels_never_count_as_delta_hits():
    """Depths near 1 and a prediction ``1/z + c`` on the foreground: the fit ``1/z = pred - c`` is exact, so AbsRel
    is 0 and every foreground pixel a hit. The background's aligned disparity is ``-c``: for ``c = 1`` capped to
    depth ``10 * max z = 12`` (an error of 11 against a placeholder depth 1), for ``c = -1`` depth 1 (a hit
    against that placeholder); neither may enter the scores."""
    depth = torch.tensor([[0.8, 0.9, 1.0], [1.1, 1.2, 0.0], [0.0, 0.0, 0.0]], dtype=torch.float64)[None]
    fg = depth > 0
    for shift in (1.0, -1.0):
        pred = torch.where(fg, 1 / depth.clamp_min(1e-3) + shift, torch.full_like(depth, 7.0))
        scores = affine_invariant_scores(pred, depth)
        assert scores.abs_rel.item() == pytest.approx(0.0, abs=1e-6) and scores.delta1.item() == 1.0


def test_normalised_values_by_hand_and_the_documented_range():
    """Foreground ``[-50, -1, 0 x 6, 1, 50]``: median 0, mean absolute deviation 102 / 10 = 10.2, so the outliers
    (-4.9, +4.9) clamp to the documented bounds -4 and 4 and ``+-1`` become ``+-1/10.2``; the background is the
    documented -5 (the range ``[-5, 4]`` the shipped models were trained with)."""
    fg = [-50.0, -1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 50.0]
    disp = torch.tensor(fg + [123.0, -7.0]).reshape(1, 3, 4)
    mask = torch.tensor([True] * 10 + [False, False]).reshape(1, 3, 4)
    out = normalize_disparity(disp, mask).reshape(-1).tolist()
    expected = [-4.0, -1 / 10.2, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1 / 10.2, 4.0, -5.0, -5.0]
    assert out == pytest.approx(expected, abs=1e-6)
