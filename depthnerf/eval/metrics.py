"""Image metrics of the SRN protocol, computed the way pixelNeRF computes them.

Facts checked in pixelNeRF's ``eval/eval.py`` and ``eval/calc_metrics.py``:

- Images are ``H x W x 3`` floats in ``[0, 1]``; the render is clamped to ``[0, 1]`` first (eval.py clamps the
  renderer's output). ``calc_metrics.py`` re-reads renders that eval.py wrote as 8-bit PNG by *truncation*
  (``(x * 255).astype(uint8)``); :attr:`ImageMetricsConfig.quantize_pred` reproduces that path (the default of
  ``depthnerf eval``, ``--scored png8``), the class default is eval.py's float path (training validation).
- PSNR: scikit-image's ``10 log10(data_range^2 / MSE)`` with ``data_range = 1``, MSE over all pixels and channels.
- SSIM: scikit-image with ``data_range = 1`` over all channels (``multichannel=True`` then, ``channel_axis=-1``
  now): the mean over channels of per-channel SSIM, with the old ``compare_ssim`` defaults that pixelNeRF got and
  that we pass explicitly: a 7x7 *uniform* window (``gaussian_weights=False``), sample covariance
  (``use_sample_covariance=True``), ``K1 = 0.01``, ``K2 = 0.03``, computed in float64 (as the old function did).
  That is :attr:`ImageMetricsConfig.ssim_window` ``"uniform7"``, the default. Later papers use an 11x11 Gaussian
  window (sigma 1.5, population covariance), in two spellings that differ at the image border (see
  :data:`SSIM_WINDOWS`): ``"gaussian11"`` (scikit-image's ``gaussian_weights=True, sigma=1.5,
  use_sample_covariance=False``, Wang et al. 2004: the 5-pixel border is left out) and ``"gaussian11-zeropad"``
  (the ``ssim()`` of 3D Gaussian Splatting's ``utils/loss_utils.py``, which Splatter Image's ``eval.py`` calls:
  the image is zero-padded and every pixel counts; computed here in float64, there in float32).
- LPIPS: the ``lpips`` package, VGG trunk, v0.1 linear layers, inputs scaled to ``[-1, 1]``.
- Aggregation: per object, the plain mean over its evaluated views; dataset, the plain mean over objects (not
  over views): eval.py's ``total_psnr / cnt`` with ``cnt`` counting objects, calc_metrics.py's reduce step.

Departure (documented, tested): pixelNeRF has no cap, so a pixel-perfect render (MSE 0, e.g. the all-white object
of the SRN cars test set rendered exactly white) gives PSNR ``inf``. Here MSE is floored at :data:`MSE_FLOOR`
(1e-10, i.e. PSNR <= 100 dB). For a 128x128 image that one 8-bit step in one channel of one pixel already moves
above the floor (MSE >= 3.1e-10), so the cap changes nothing but the degenerate case. SSIM of two constant
images is finite in scikit-image (``C1, C2 > 0``); it is checked anyway.

LPIPS needs the torchvision ImageNet trunk, which the ``lpips`` package does not ship and which must not be
downloaded: :func:`lpips_status` looks for the trunk file in the torch hub cache (or a given path) and
:func:`load_lpips` returns ``None`` when it is missing; summaries then say ``"unavailable: <reason>"``.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from jaxtyping import Float
from scipy.ndimage import correlate1d
from skimage.metrics import structural_similarity

from depthnerf.errors import DepthnerfError
from depthnerf.state_dicts import read_state_dict

MSE_FLOOR = 1e-10
"""Smallest MSE used in PSNR: caps PSNR at 100 dB so a pixel-perfect render stays finite."""
SSIM_WIN_SIZE = 7
"""SSIM window side of ``uniform7`` (scikit-image's former default, what pixelNeRF used)."""
SSIM_WINDOWS = {
    "uniform7": "7x7 uniform window, sample covariance, 3-pixel border left out (pixelNeRF: scikit-image's "
                "compare_ssim defaults)",
    "gaussian11": "11x11 Gaussian window sigma 1.5, population covariance, 5-pixel border left out (Wang et al. "
                  "2004; scikit-image gaussian_weights=True, sigma=1.5, use_sample_covariance=False)",
    "gaussian11-zeropad": "11x11 Gaussian window sigma 1.5, population covariance, zero-padded image, mean over "
                          "every pixel (3D Gaussian Splatting's ssim(), as Splatter Image's eval.py calls it)",
}
"""The SSIM variants :func:`ssim` computes (``ImageMetricsConfig.ssim_window``, ``depthnerf eval --ssim``)."""
SSIM_WINDOW_SIDE = {"uniform7": SSIM_WIN_SIZE, "gaussian11": 11, "gaussian11-zeropad": 11}
"""Window side of each SSIM variant (the smallest image it measures)."""
GAUSSIAN_SIGMA = 1.5
"""Standard deviation (pixels) of the Gaussian SSIM windows."""
TRUNK_WEIGHTS = {"vgg": "VGG16_Weights.IMAGENET1K_V1", "alex": "AlexNet_Weights.IMAGENET1K_V1"}
"""The torchvision weight enums whose ImageNet trunks LPIPS uses."""


@dataclass(frozen=True)
class ImageMetricsConfig:
    """How renders are compared with ground truth."""

    quantize_pred: bool = False
    """Truncate the render to 8 bit before measuring (pixelNeRF calc_metrics.py path); False = eval.py path."""
    ssim_window: str = "uniform7"
    """SSIM variant, a key of :data:`SSIM_WINDOWS` (``uniform7``: pixelNeRF's)."""
    lpips_batch: int = 32
    """Views per LPIPS forward pass (pixelNeRF's default)."""


@dataclass(frozen=True)
class LpipsConfig:
    """Where LPIPS gets its weights (never from the network)."""

    net: str = "vgg"
    """Trunk: ``vgg`` (pixelNeRF) or ``alex``."""
    trunk_path: Path | None = None
    """torchvision state dict of the trunk; None = the torch hub cache file torchvision itself would use."""


@dataclass(frozen=True)
class ViewMetrics:
    """Metrics of one rendered view."""

    psnr: float
    """dB, MSE floored at :data:`MSE_FLOOR`."""
    ssim: float
    """SSIM in the variant :attr:`ImageMetricsConfig.ssim_window` (:func:`ssim`), mean over channels."""
    lpips: float | None
    """LPIPS (VGG), None when LPIPS is unavailable."""


@dataclass(frozen=True)
class ObjectMetrics:
    """Metrics of one object: its views and their plain means."""

    object_id: str
    """The object's folder name."""
    views: list[ViewMetrics]
    """One entry per evaluated (target) view."""
    psnr: float
    """Mean PSNR over ``views``."""
    ssim: float
    """Mean SSIM over ``views``."""
    lpips: float | None
    """Mean LPIPS over ``views``, None when unavailable."""


def _as_image(x: np.ndarray | torch.Tensor, what: str) -> np.ndarray:
    """``H x W x 3`` float64 copy of an image given as numpy or torch; finite values required."""
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 3 or x.shape[-1] != 3:
        raise DepthnerfError(f"{what}: expected an H x W x 3 image, got shape {tuple(x.shape)}")
    if not np.isfinite(x).all():
        raise DepthnerfError(f"{what}: image has non-finite values")
    return x


def _pair(pred, gt, config: ImageMetricsConfig) -> tuple[np.ndarray, np.ndarray]:
    """Checked ``(pred, gt)``: pred clamped (and optionally 8-bit truncated), gt required in [0, 1]."""
    pred, gt = _as_image(pred, "render"), _as_image(gt, "ground truth")
    if pred.shape != gt.shape:
        raise DepthnerfError(f"render shape {pred.shape} differs from ground truth shape {gt.shape}")
    if gt.min() < -1e-6 or gt.max() > 1 + 1e-6:
        raise DepthnerfError(f"ground truth: values outside [0, 1] (min {gt.min():.4g}, max {gt.max():.4g})")
    pred = np.clip(pred, 0.0, 1.0)
    if config.quantize_pred:
        pred = np.floor(pred * 255.0) / 255.0
    return pred, np.clip(gt, 0.0, 1.0)


def psnr(pred: Float[np.ndarray, "H W 3"], gt: Float[np.ndarray, "H W 3"],
         config: ImageMetricsConfig = ImageMetricsConfig()) -> float:
    """PSNR in dB with ``data_range = 1`` (scikit-image's formula), MSE floored at :data:`MSE_FLOOR`."""
    pred, gt = _pair(pred, gt, config)
    mse = float(np.mean(np.square(pred - gt), dtype=np.float64))
    return 10.0 * math.log10(1.0 / max(mse, MSE_FLOOR))


def gaussian_window_1d(side: int = 11, sigma: float = GAUSSIAN_SIGMA) -> Float[np.ndarray, " K"]:
    """Normalised 1D Gaussian weights of a ``side``-tap window (the 2D window is their outer product)."""
    x = np.arange(side, dtype=np.float64) - side // 2
    g = np.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def _ssim_zeropad(pred: np.ndarray, gt: np.ndarray, k1: float = 0.01, k2: float = 0.03) -> float:
    """SSIM as 3D Gaussian Splatting's ``ssim()``: Gaussian-weighted local statistics of the zero-padded images
    (same-size maps), population covariance, the SSIM map averaged over every pixel and channel."""
    g = gaussian_window_1d()

    def blur(x: np.ndarray) -> np.ndarray:
        x = correlate1d(x, g, axis=0, mode="constant", cval=0.0)
        return correlate1d(x, g, axis=1, mode="constant", cval=0.0)

    mu_x, mu_y = blur(pred), blur(gt)
    var_x, var_y = blur(pred * pred) - mu_x**2, blur(gt * gt) - mu_y**2
    cov = blur(pred * gt) - mu_x * mu_y
    c1, c2 = k1**2, k2**2
    ssim_map = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / ((mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2))
    return float(ssim_map.mean())


def ssim(pred: Float[np.ndarray, "H W 3"], gt: Float[np.ndarray, "H W 3"],
         config: ImageMetricsConfig = ImageMetricsConfig()) -> float:
    """SSIM over all channels in the variant ``config.ssim_window`` (default pixelNeRF's; module docstring)."""
    pred, gt = _pair(pred, gt, config)
    window = config.ssim_window
    if window not in SSIM_WINDOWS:
        raise DepthnerfError(f"unknown SSIM variant {window!r} (choose {', '.join(SSIM_WINDOWS)})")
    side = SSIM_WINDOW_SIDE[window]
    if min(pred.shape[:2]) < side:
        raise DepthnerfError(f"image {pred.shape[0]}x{pred.shape[1]} is smaller than the SSIM window "
                             f"{side}x{side}")
    if window == "uniform7":
        value = float(structural_similarity(pred, gt, win_size=SSIM_WIN_SIZE, data_range=1.0, channel_axis=-1,
                                            gaussian_weights=False, use_sample_covariance=True, K1=0.01, K2=0.03))
    elif window == "gaussian11":
        value = float(structural_similarity(pred, gt, data_range=1.0, channel_axis=-1, gaussian_weights=True,
                                            sigma=GAUSSIAN_SIGMA, use_sample_covariance=False, K1=0.01, K2=0.03))
    else:
        value = _ssim_zeropad(pred, gt)
    if not math.isfinite(value):
        raise DepthnerfError(f"SSIM is not finite ({value}) for images of shape {pred.shape}")
    return value


@dataclass(frozen=True)
class LpipsStatus:
    """Whether LPIPS can run offline, and why not."""

    available: bool
    """True when the package, its linear weights and the trunk weights are all present locally."""
    reason: str
    """``"ok"`` or ``"unavailable: <reason>"``."""


def _linear_file(config: LpipsConfig) -> Path:
    """The v0.1 linear-layer weights the ``lpips`` package ships for ``config.net`` (the package must import)."""
    import lpips

    return Path(lpips.__file__).parent / "weights" / "v0.1" / f"{config.net}.pth"


def _trunk_file(config: LpipsConfig) -> Path:
    """The trunk weight file: the given path, or torchvision's own hub-cache file name."""
    if config.trunk_path is not None:
        return Path(config.trunk_path)
    from torchvision.models import get_weight

    url = get_weight(TRUNK_WEIGHTS[config.net]).url
    return Path(torch.hub.get_dir()) / "checkpoints" / url.rsplit("/", 1)[-1]


def lpips_status(config: LpipsConfig = LpipsConfig()) -> LpipsStatus:
    """Check, without loading or downloading anything, that LPIPS can run."""
    if config.net not in TRUNK_WEIGHTS:
        return LpipsStatus(False, f"unavailable: unknown LPIPS trunk {config.net!r} (use {sorted(TRUNK_WEIGHTS)})")
    try:
        linear = _linear_file(config)
    except ImportError:
        return LpipsStatus(False, "unavailable: the 'lpips' package is not installed")
    if not linear.is_file():
        return LpipsStatus(False, f"unavailable: LPIPS linear weights missing ({linear})")
    trunk = _trunk_file(config)
    if not trunk.is_file():
        return LpipsStatus(False, f"unavailable: {config.net} ImageNet trunk weights not found locally ({trunk})")
    return LpipsStatus(True, "ok")


class LpipsMetric:
    """LPIPS on ``[0, 1]`` images (scaled to ``[-1, 1]`` inside, as pixelNeRF does), CPU or GPU."""

    def __init__(self, model: torch.nn.Module, device: torch.device | str = "cpu"):
        self.model = model.to(device).eval()
        self.device = torch.device(device)

    @torch.no_grad()
    def per_view(self, preds: Float[np.ndarray, "V H W 3"], gts: Float[np.ndarray, "V H W 3"],
                 batch: int = 32) -> Float[np.ndarray, " V"]:
        """LPIPS of each view pair; images already checked and in ``[0, 1]``."""
        out = []
        for start in range(0, len(preds), batch):
            p = torch.as_tensor(np.asarray(preds[start:start + batch]), dtype=torch.float32, device=self.device)
            g = torch.as_tensor(np.asarray(gts[start:start + batch]), dtype=torch.float32, device=self.device)
            p, g = (x.permute(0, 3, 1, 2) * 2.0 - 1.0 for x in (p, g))
            out.append(self.model(p, g).reshape(-1).double().cpu().numpy())
        return np.concatenate(out) if out else np.zeros(0)


def load_lpips(config: LpipsConfig = LpipsConfig(), device: torch.device | str = "cpu") -> LpipsMetric | None:
    """LPIPS from local files only (``torch.load(weights_only=True)``), or None when :func:`lpips_status`
    says it is unavailable. A weights file that exists but cannot be read or does not fit raises
    :class:`DepthnerfError` naming that file."""
    status = lpips_status(config)
    if not status.available:
        return None
    import lpips

    linear_path, trunk_path = _linear_file(config), _trunk_file(config)
    linear, trunk = read_state_dict(linear_path, "LPIPS weights"), read_state_dict(trunk_path, "LPIPS weights")
    with warnings.catch_warnings():  # lpips passes torchvision's deprecated `pretrained=False`
        warnings.simplefilter("ignore")
        model = lpips.LPIPS(pretrained=False, net=config.net, version="0.1", pnet_rand=True, verbose=False)
    state = dict(linear)
    for name in model.state_dict():
        if name.startswith("net.slice"):  # net.slice3.6.weight <- features.6.weight
            key = "features." + name.split(".", 2)[2]
            if key not in trunk:
                raise DepthnerfError(f"{trunk_path}: not a torchvision {config.net} state dict (no {key})")
            state[name] = trunk[key]
    try:  # scaling_layer.* are constant buffers and lins.* alias lin0..lin4: everything else must be loaded
        result = model.load_state_dict(state, strict=False)
    except RuntimeError as err:
        first = str(err).splitlines()[0]
        raise DepthnerfError(f"{trunk_path}: LPIPS weights do not fit the {config.net} trunk ({first})") from None
    missing = [k for k in result.missing_keys if not k.startswith(("scaling_layer.", "lins."))]
    if missing or result.unexpected_keys:
        raise DepthnerfError(f"{linear_path}: LPIPS weights incomplete (missing {missing[:3]}, "
                             f"unexpected {result.unexpected_keys[:3]})")
    return LpipsMetric(model, device)


def object_metrics(object_id: str, preds: Sequence[np.ndarray] | np.ndarray, gts: Sequence[np.ndarray] | np.ndarray,
                   config: ImageMetricsConfig = ImageMetricsConfig(), lpips: LpipsMetric | None = None) -> ObjectMetrics:
    """Per-view PSNR/SSIM (and LPIPS when given) of one object's target views, and their plain means."""
    if len(preds) != len(gts) or len(preds) == 0:
        raise DepthnerfError(f"object {object_id}: {len(preds)} renders for {len(gts)} ground-truth views")
    pairs = [_pair(p, g, config) for p, g in zip(preds, gts, strict=True)]
    lp = None
    if lpips is not None:
        lp = lpips.per_view(np.stack([p for p, _ in pairs]), np.stack([g for _, g in pairs]), config.lpips_batch)
    views = []
    exact = ImageMetricsConfig(ssim_window=config.ssim_window)  # pairs already clamped/quantised: as they are
    for i, (p, g) in enumerate(pairs):
        views.append(ViewMetrics(psnr=psnr(p, g, exact), ssim=ssim(p, g, exact),
                                 lpips=None if lp is None else float(lp[i])))
    return ObjectMetrics(
        object_id=object_id, views=views,
        psnr=float(np.mean([v.psnr for v in views])), ssim=float(np.mean([v.ssim for v in views])),
        lpips=None if lp is None else float(np.mean(lp)),
    )


def summarize(objects: Sequence[ObjectMetrics], lpips_reason: str | None = None) -> dict:
    """Dataset metrics: plain means over objects of the per-object means (pixelNeRF's aggregation).

    Returns the metric part of ``summary.json``: ``psnr``, ``ssim``, ``lpips`` (None unless every object has
    it), ``lpips_status`` (``"ok"`` or ``lpips_reason``), ``objects``, ``views``, ``aggregation`` and
    ``per_object`` (id, views, psnr, ssim, lpips). The eval driver adds the provenance fields.
    """
    if not objects:
        raise DepthnerfError("no objects were evaluated: nothing to summarise")
    have_lpips = all(o.lpips is not None for o in objects)
    return {
        "psnr": float(np.mean([o.psnr for o in objects])),
        "ssim": float(np.mean([o.ssim for o in objects])),
        "lpips": float(np.mean([o.lpips for o in objects])) if have_lpips else None,
        "lpips_status": "ok" if have_lpips else (lpips_reason or "unavailable: not computed"),
        "objects": len(objects),
        "views": sum(len(o.views) for o in objects),
        "aggregation": "mean over objects of the per-object mean over target views (pixelNeRF)",
        "per_object": [{"object_id": o.object_id, "views": len(o.views), "psnr": o.psnr, "ssim": o.ssim,
                        "lpips": o.lpips} for o in objects],
    }
