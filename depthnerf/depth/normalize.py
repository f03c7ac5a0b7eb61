"""Per-image normalisation of a relative disparity map into the network's depth-prior input.

Every backend (``depth-anything-v2``, ``bundled``, ``oracle``) outputs *relative disparity*: larger = closer,
defined only up to an unknown positive scale ``a`` and shift ``b``. :func:`normalize_disparity` removes that
ambiguity with robust statistics over the **foreground** pixels only (``mask`` True = object):

    m = median of the foreground disparities          (lower median for an even count)
    s = mean |d - m| over the foreground               (mean absolute deviation around the median)
    n = clamp((d - m) / max(s, SCALE_FLOOR), -FOREGROUND_CLAMP, FOREGROUND_CLAMP)      on the foreground
    n = BACKGROUND_VALUE                                                                on the background

so ``normalize(a * d + b) == normalize(d)`` for every ``a > 0`` (exactly, up to float rounding). The output is
bounded to ``[BACKGROUND_VALUE, FOREGROUND_CLAMP] = [-5, 4]``; background pixels are the constant ``-5``, one unit
*below* (i.e. farther than) the farthest representable foreground value, so an encoder can always tell object
from background, whatever the backend. An empty mask (an all-white image) gives the background constant
everywhere; a constant foreground gives 0 on the foreground. Neither ever produces NaN.
"""

from __future__ import annotations

import torch
from jaxtyping import Bool, Float
from torch import Tensor

FOREGROUND_CLAMP = 4.0
"""Normalised foreground disparities are clamped to ``[-4, 4]`` (about 4 mean absolute deviations)."""

BACKGROUND_VALUE = -5.0
"""The constant every background pixel gets (farther than any foreground value)."""

SCALE_FLOOR = 1e-8
"""Lower bound on the deviation ``s`` so a constant foreground does not divide by zero."""


def foreground_median_and_deviation(disp: Float[Tensor, "N P"], mask: Bool[Tensor, "N P"]
                                    ) -> tuple[Float[Tensor, " N"], Float[Tensor, " N"], Float[Tensor, " N"]]:
    """Foreground median ``m``, mean absolute deviation ``s`` (around ``m``) and pixel count of each row.

    Rows without foreground get ``m = 0``, ``s = 0``, count 0.
    """
    count = mask.sum(dim=-1)
    masked = torch.where(mask, disp, torch.full_like(disp, float("nan")))
    median = torch.nanmedian(masked, dim=-1).values
    median = torch.where(count > 0, median, torch.zeros_like(median))
    dev = torch.where(mask, (disp - median[:, None]).abs(), torch.zeros_like(disp)).sum(dim=-1)
    dev = dev / count.clamp_min(1).to(disp.dtype)
    return median, dev, count


def normalize_disparity(disp: Float[Tensor, "*B H W"], mask: Bool[Tensor, "*B H W"], *,
                        clamp: float = FOREGROUND_CLAMP,
                        background: float = BACKGROUND_VALUE) -> Float[Tensor, "*B H W"]:
    """Normalise relative disparity per image over its foreground (see the module docstring); float32 out."""
    if disp.shape != mask.shape:
        raise ValueError(f"disparity {tuple(disp.shape)} and mask {tuple(mask.shape)} shapes differ")
    shape = disp.shape
    flat = disp.reshape(-1, shape[-2] * shape[-1]).float()
    fg = mask.reshape(flat.shape).bool() & torch.isfinite(flat)
    flat = torch.where(fg, flat, torch.zeros_like(flat))
    median, dev, _ = foreground_median_and_deviation(flat, fg)
    out = ((flat - median[:, None]) / dev.clamp_min(SCALE_FLOOR)[:, None]).clamp(-clamp, clamp)
    out = torch.where(fg, out, torch.full_like(out, background))
    return out.reshape(shape)
