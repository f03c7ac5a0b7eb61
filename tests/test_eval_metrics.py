"""Image metrics against closed forms, scikit-image, and a brute-force SSIM loop."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from skimage.metrics import peak_signal_noise_ratio

from depthnerf.errors import DepthnerfError
from depthnerf.eval.metrics import (
    MSE_FLOOR,
    ImageMetricsConfig,
    LpipsConfig,
    LpipsMetric,
    load_lpips,
    lpips_status,
    object_metrics,
    psnr,
    ssim,
    summarize,
)


def _rand(shape, seed):
    return np.random.default_rng(seed).random(shape)


def _ssim_reference(x: np.ndarray, y: np.ndarray, win: int = 7) -> float:
    """Textbook SSIM, one window position at a time: uniform window, sample (ddof=1) statistics, valid region."""
    c1, c2 = 0.01**2, 0.03**2
    vals = []
    for ch in range(x.shape[-1]):
        for i in range(x.shape[0] - win + 1):
            for j in range(x.shape[1] - win + 1):
                a, b = x[i:i + win, j:j + win, ch].ravel(), y[i:i + win, j:j + win, ch].ravel()
                ma, mb = a.mean(), b.mean()
                va, vb = a.var(ddof=1), b.var(ddof=1)
                cov = ((a - ma) * (b - mb)).sum() / (a.size - 1)
                vals.append(((2 * ma * mb + c1) * (2 * cov + c2)) / ((ma**2 + mb**2 + c1) * (va + vb + c2)))
    return float(np.mean(vals))


def test_psnr_closed_form_and_skimage():
    gt = np.full((16, 16, 3), 0.5)
    assert psnr(gt + 0.1, gt) == pytest.approx(20.0, abs=1e-9)  # MSE 0.01
    pred, gt = _rand((20, 24, 3), 0), _rand((20, 24, 3), 1)
    assert psnr(pred, gt) == pytest.approx(peak_signal_noise_ratio(gt, pred, data_range=1.0), abs=1e-9)


def test_psnr_is_capped_for_a_perfect_render_of_an_empty_object():
    white = np.ones((32, 32, 3))
    assert psnr(white, white) == pytest.approx(10 * math.log10(1 / MSE_FLOOR)) == pytest.approx(100.0)
    one_step = white.copy()
    one_step[0, 0, 0] -= 1 / 255  # the smallest 8-bit difference stays below the cap
    assert psnr(one_step, white) < 100.0


def test_ssim_matches_brute_force_loop():
    gt = _rand((12, 13, 3), 2)
    pred = np.clip(gt + 0.2 * _rand((12, 13, 3), 3) - 0.1, 0, 1)
    assert ssim(pred, gt) == pytest.approx(_ssim_reference(pred, gt), abs=1e-10)


def _gaussian_ssim_reference(x: np.ndarray, y: np.ndarray, zero_pad: bool) -> float:
    """Textbook Gaussian SSIM, one pixel at a time: 11x11 weights exp(-r^2 / (2 * 1.5^2)) normalised to sum 1,
    weighted (population) statistics; ``zero_pad``: every pixel, outside values 0, else the valid region only."""
    c1, c2, half = 0.01**2, 0.03**2, 5
    d = np.arange(-half, half + 1)
    w = np.exp(-(d[:, None] ** 2 + d[None, :] ** 2) / (2 * 1.5**2))
    w /= w.sum()
    pad = half if zero_pad else 0
    xp = np.pad(x, ((pad, pad), (pad, pad), (0, 0)))
    yp = np.pad(y, ((pad, pad), (pad, pad), (0, 0)))
    vals = []
    for ch in range(x.shape[-1]):
        for i in range(half, xp.shape[0] - half):
            for j in range(half, xp.shape[1] - half):
                a = xp[i - half:i + half + 1, j - half:j + half + 1, ch]
                b = yp[i - half:i + half + 1, j - half:j + half + 1, ch]
                ma, mb = (w * a).sum(), (w * b).sum()
                va, vb, cov = (w * (a - ma) ** 2).sum(), (w * (b - mb) ** 2).sum(), (w * (a - ma) * (b - mb)).sum()
                vals.append(((2 * ma * mb + c1) * (2 * cov + c2)) / ((ma**2 + mb**2 + c1) * (va + vb + c2)))
    return float(np.mean(vals))


@pytest.mark.parametrize("window, zero_pad", [("gaussian11", False), ("gaussian11-zeropad", True)])
def test_gaussian_ssim_matches_brute_force_loop(window, zero_pad):
    gt = _rand((16, 17, 3), 7)
    pred = np.clip(gt + 0.3 * _rand((16, 17, 3), 8) - 0.15, 0, 1)
    value = ssim(pred, gt, ImageMetricsConfig(ssim_window=window))
    assert value == pytest.approx(_gaussian_ssim_reference(pred, gt, zero_pad), abs=1e-10)
    assert value != pytest.approx(ssim(pred, gt), abs=1e-3)  # a different number from pixelNeRF's uniform7


@pytest.mark.parametrize("window, side", [("uniform7", 7), ("gaussian11", 11), ("gaussian11-zeropad", 11)])
def test_ssim_of_an_image_exactly_the_window_size(window, side):
    """The smallest image a variant measures is one window: uniform7 at 7x7, the Gaussian ones at 11x11."""
    gt = _rand((side, side, 3), 10)
    pred = np.clip(gt + 0.3 * _rand((side, side, 3), 11) - 0.15, 0, 1)
    value = ssim(pred, gt, ImageMetricsConfig(ssim_window=window))
    expect = (_ssim_reference(pred, gt) if window == "uniform7"
              else _gaussian_ssim_reference(pred, gt, zero_pad=window.endswith("zeropad")))
    assert value == pytest.approx(expect, abs=1e-10)
    with pytest.raises(DepthnerfError, match="smaller than the SSIM window"):
        ssim(pred[:-1], gt[:-1], ImageMetricsConfig(ssim_window=window))


def test_ssim_variant_is_checked_and_needs_its_window():
    img = _rand((10, 10, 3), 9)
    assert math.isfinite(ssim(img, img))  # 10x10 fits the 7x7 window ...
    for window in ("gaussian11", "gaussian11-zeropad"):
        with pytest.raises(DepthnerfError, match="smaller than the SSIM window 11x11"):  # ... not the 11x11 one
            ssim(img, img, ImageMetricsConfig(ssim_window=window))
    with pytest.raises(DepthnerfError, match="unknown SSIM variant"):
        ssim(img, img, ImageMetricsConfig(ssim_window="gaussian7"))


def test_ssim_of_constant_images_is_finite_closed_form():
    white, grey = np.ones((16, 16, 3)), np.full((16, 16, 3), 0.5)
    assert ssim(white, white) == pytest.approx(1.0)
    c1 = 0.01**2  # zero variance: the contrast-structure term is C2/C2 = 1
    assert ssim(grey, white) == pytest.approx((2 * 0.5 + c1) / (0.25 + 1 + c1), abs=1e-12)


def test_float32_and_torch_inputs_are_measured_in_float64():
    p32, g32 = _rand((16, 16, 3), 4).astype(np.float32), _rand((16, 16, 3), 5).astype(np.float32)
    ref = ssim(p32.astype(np.float64), g32.astype(np.float64))
    assert ssim(p32, g32) == ref
    assert ssim(torch.from_numpy(p32), torch.from_numpy(g32)) == ref
    assert psnr(torch.from_numpy(p32), torch.from_numpy(g32)) == psnr(p32.astype(np.float64), g32.astype(np.float64))


def test_render_is_clamped_and_optionally_truncated_to_8_bit():
    gt = np.round(_rand((16, 16, 3), 6) * 255) / 255
    over = gt.copy()
    over[gt == gt.max()] = 1.5  # out-of-range render values are clamped like pixelNeRF's eval.py
    assert psnr(over, gt) == psnr(np.clip(over, 0, 1), gt)
    pred = np.clip(gt + 0.9 / 255, 0, 1)  # below the next 8-bit level: truncation gives back gt where gt < 1
    mask = gt < 1
    expected_mse = np.mean(np.where(mask, 0.9 / 255, pred - gt) ** 2)
    assert psnr(pred, gt) == pytest.approx(10 * math.log10(1 / expected_mse))
    assert psnr(pred, gt, ImageMetricsConfig(quantize_pred=True)) == pytest.approx(100.0)


@pytest.mark.parametrize(
    ("pred", "gt", "match"),
    [
        (np.zeros((8, 8, 3)), np.zeros((8, 9, 3)), "differs"),
        (np.zeros((8, 8)), np.zeros((8, 8)), "H x W x 3"),
        (np.full((8, 8, 3), np.nan), np.zeros((8, 8, 3)), "non-finite"),
        (np.zeros((8, 8, 3)), np.full((8, 8, 3), 2.0), r"outside \[0, 1\]"),
        (np.zeros((5, 8, 3)), np.zeros((5, 8, 3)), "smaller than the SSIM window"),
    ],
)
def test_bad_images_raise(pred, gt, match):
    with pytest.raises(DepthnerfError, match=match):
        ssim(pred, gt)


def test_aggregation_is_mean_over_objects_of_view_means():
    gt = np.full((16, 16, 3), 0.5)
    a = object_metrics("a", [gt + 0.1], [gt])  # 20 dB
    b = object_metrics("b", [gt + 0.01, gt + 0.01, gt + 0.1], [gt, gt, gt])  # 40, 40, 20 dB
    assert a.psnr == pytest.approx(20.0) and b.psnr == pytest.approx(100 / 3)
    assert [v.psnr for v in b.views] == pytest.approx([40.0, 40.0, 20.0])
    summary = summarize([a, b], lpips_reason="unavailable: test")
    assert summary["psnr"] == pytest.approx((20.0 + 100 / 3) / 2)  # not the per-view mean (30 dB)
    assert summary["ssim"] == pytest.approx((a.ssim + b.ssim) / 2)
    assert (summary["objects"], summary["views"]) == (2, 4)
    assert summary["lpips"] is None and summary["lpips_status"] == "unavailable: test"
    assert [o["object_id"] for o in summary["per_object"]] == ["a", "b"]
    with pytest.raises(DepthnerfError):
        summarize([])
    with pytest.raises(DepthnerfError, match="2 renders for 1"):
        object_metrics("c", [gt, gt], [gt])


def test_lpips_reports_unavailable_instead_of_a_number(tmp_path):
    missing = LpipsConfig(trunk_path=tmp_path / "nope.pth")
    status = lpips_status(missing)
    assert not status.available and status.reason.startswith("unavailable:")
    assert load_lpips(missing) is None
    assert lpips_status(LpipsConfig(net="resnet")).reason.startswith("unavailable: unknown LPIPS trunk")
    default = lpips_status()  # whatever this machine has: either ok or a stated reason, never a guess
    assert default.available == (default.reason == "ok") and (default.available or "unavailable:" in default.reason)


def test_lpips_errors_name_the_file_that_is_bad(tmp_path, monkeypatch):
    """The linear-layer weights the lpips package ships and the trunk are two files: an unreadable or non-dict one
    is named, not the other."""
    lpips = pytest.importorskip("lpips")
    package = tmp_path / "lpips"
    linear = package / "weights" / "v0.1" / "alex.pth"
    linear.parent.mkdir(parents=True)
    monkeypatch.setattr(lpips, "__file__", str(package / "__init__.py"))
    trunk = tmp_path / "alexnet.pth"
    torch.save({"features.0.weight": torch.zeros(1)}, trunk)
    linear.write_bytes(b"not a checkpoint")
    with pytest.raises(DepthnerfError, match="cannot read LPIPS weights") as err:
        load_lpips(LpipsConfig(net="alex", trunk_path=trunk))
    assert str(err.value).startswith(f"{linear}: ")
    torch.save([torch.zeros(1)], linear)
    with pytest.raises(DepthnerfError, match="not a state dict") as err:
        load_lpips(LpipsConfig(net="alex", trunk_path=trunk))
    assert str(err.value).startswith(f"{linear}: ")


def test_lpips_loads_local_weights_only(tmp_path):
    lpips = pytest.importorskip("lpips")
    gen = torch.Generator().manual_seed(0)  # torchvision alexnet.features: convs at indices 0, 3, 6, 8, 10
    shapes = {0: (64, 3, 11, 11), 3: (192, 64, 5, 5), 6: (384, 192, 3, 3), 8: (256, 384, 3, 3), 10: (256, 256, 3, 3)}
    state = {}
    for idx, shape in shapes.items():
        state[f"features.{idx}.weight"] = torch.randn(shape, generator=gen) * (2 / math.prod(shape[1:])) ** 0.5
        state[f"features.{idx}.bias"] = torch.zeros(shape[0])
    path = tmp_path / "alexnet.pth"
    torch.save(state, path)
    metric = load_lpips(LpipsConfig(net="alex", trunk_path=path))
    assert metric is not None
    loaded = metric.model.state_dict()
    assert torch.equal(loaded["net.slice1.0.weight"], state["features.0.weight"])
    assert torch.equal(loaded["net.slice5.10.weight"], state["features.10.weight"])
    linear = torch.load(f"{lpips.__path__[0]}/weights/v0.1/alex.pth", map_location="cpu", weights_only=True)
    assert torch.equal(metric.model.lin0.model[1].weight, linear["lin0.model.1.weight"])

    gt, pred = _rand((2, 32, 32, 3), 7), _rand((2, 32, 32, 3), 8)
    values = metric.per_view(pred, gt, batch=1)
    with torch.no_grad():  # lpips' own [0, 1] -> [-1, 1] path as the reference for our scaling
        ref = metric.model(*(torch.tensor(x, dtype=torch.float32).permute(0, 3, 1, 2) for x in (pred, gt)),
                           normalize=True).reshape(-1).numpy()
    assert values == pytest.approx(ref, rel=1e-5) and (values > 0).all()
    assert metric.per_view(gt, gt) == pytest.approx([0.0, 0.0], abs=1e-7)
    obj = object_metrics("x", list(pred), list(gt), lpips=metric)
    assert obj.lpips == pytest.approx(values.mean(), rel=1e-5) and summarize([obj])["lpips_status"] == "ok"

    del state["features.3.weight"]
    torch.save(state, path)
    with pytest.raises(DepthnerfError, match="not a torchvision alex state dict"):
        load_lpips(LpipsConfig(net="alex", trunk_path=path))
    path.write_bytes(b"not a checkpoint")
    with pytest.raises(DepthnerfError, match="cannot read LPIPS weights"):
        load_lpips(LpipsConfig(net="alex", trunk_path=path))


class _SquaredError(torch.nn.Module):
    """A stand-in perceptual distance: the mean squared difference of the [-1, 1] inputs, 4 x the [0, 1] MSE."""

    def forward(self, p: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        return ((p - g) ** 2).mean(dim=(1, 2, 3), keepdim=True)


def test_object_lpips_is_the_mean_over_views_in_batches_and_needs_every_object():
    """Three views at offsets 0.05, 0.05, 0.2 (distances 4 x 0.0025, 4 x 0.0025, 4 x 0.04), two per batch: the
    object's LPIPS is their mean 0.06 (the median would be 0.01); a dataset LPIPS needs every object's."""
    gt = np.full((8, 8, 3), 0.5)
    metric = LpipsMetric(_SquaredError())
    preds = [gt + 0.05, gt + 0.05, gt + 0.2]
    obj = object_metrics("a", preds, [gt] * 3, ImageMetricsConfig(lpips_batch=2), lpips=metric)
    assert [v.lpips for v in obj.views] == pytest.approx([0.01, 0.01, 0.16])
    assert obj.lpips == pytest.approx(0.06)
    without = object_metrics("b", [gt], [gt])
    assert summarize([obj, obj])["lpips"] == pytest.approx(0.06)
    mixed = summarize([obj, without], lpips_reason="unavailable: test")
    assert mixed["lpips"] is None and mixed["lpips_status"] == "unavailable: test"
