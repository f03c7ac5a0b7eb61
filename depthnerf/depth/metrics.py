"""Affine-invariant depth accuracy: AbsRel and delta<1.25 after scale-and-shift alignment in disparity space.

The standard protocol for relative (affine-invariant) depth estimators, per image, on foreground pixels
(ground-truth z-depth ``> 0``) only:

1. least-squares scale ``a`` and shift ``b`` minimising ``sum (a * pred + b - 1/z_gt)^2`` over the foreground
   (closed form from the 2x2 normal equations; a constant prediction gets ``a = 0``, ``b = mean(1/z_gt)``);
2. aligned disparity ``a * pred + b``, clamped below at ``1 / (DEPTH_CAP_FACTOR * max z_gt)`` so it stays positive;
3. predicted depth ``1 / aligned``; ``AbsRel = mean |z - z_gt| / z_gt``, ``delta1 = mean[max(z/z_gt, z_gt/z) < 1.25]``.

Images are scored separately and the dataset figure is the mean over images (images without foreground are not
scored and not counted).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from jaxtyping import Bool, Float
from torch import Tensor

DEPTH_CAP_FACTOR = 10.0
"""Aligned depths are capped at this multiple of the image's largest ground-truth depth (keeps 1/disp finite)."""

DELTA_THRESHOLD = 1.25
"""Threshold of the delta accuracy."""


@dataclass
class DepthScores:
    """Per-image affine-invariant depth scores (N images)."""

    abs_rel: Float[Tensor, " N"]
    """Mean absolute relative depth error over the image's foreground."""
    delta1: Float[Tensor, " N"]
    """Fraction of foreground pixels with ``max(z/z_gt, z_gt/z) < 1.25``."""
    valid: Bool[Tensor, " N"]
    """False for images without any foreground (their scores are 0 and must be ignored)."""


def fit_scale_shift(x: Float[Tensor, "B N"], y: Float[Tensor, "B N"], mask: Bool[Tensor, "B N"],
                    eps: float = 1e-12) -> tuple[Float[Tensor, " B"], Float[Tensor, " B"]]:
    """Per-row least squares ``min_{s,b} sum_mask (s x + b - y)^2`` in closed form (differentiable).

    ``s = cov(x, y) / var(x)``, ``b = mean(y) - s mean(x)`` over the masked entries (masked-out entries may hold
    anything, even inf/NaN). A row with constant ``x`` gets ``s = 0``, ``b = mean(y)``; an empty row ``s = b = 0``.
    Computed in float64 (cheap for ``B x N``; the centred moments lose precision in float32), returned in
    ``y``'s dtype.
    """
    out_dtype = y.dtype
    x, y = x.double(), y.double()
    m = mask.to(x.dtype)
    xs = torch.where(mask, x, torch.zeros_like(x))
    ys = torch.where(mask, y, torch.zeros_like(y))
    n = m.sum(-1).clamp_min(1.0)
    mx, my = xs.sum(-1) / n, ys.sum(-1) / n
    dx, dy = (xs - mx[:, None]) * m, (ys - my[:, None]) * m
    var, cov = (dx * dx).sum(-1) / n, (dx * dy).sum(-1) / n
    s = torch.where(var > eps, cov / var.clamp_min(eps), torch.zeros_like(cov))
    return s.to(out_dtype), (my - s * mx).to(out_dtype)


def align_disparity(pred: Float[Tensor, "N H W"], target: Float[Tensor, "N H W"],
                    mask: Bool[Tensor, "N H W"]) -> Float[Tensor, "N H W"]:
    """``pred`` mapped by its per-image least-squares scale and shift onto ``target`` (fitted on ``mask``)."""
    n = pred.shape[0]
    a, b = fit_scale_shift(pred.reshape(n, -1), target.reshape(n, -1), mask.reshape(n, -1))
    return pred * a[:, None, None] + b[:, None, None]


def affine_invariant_scores(pred_disp: Float[Tensor, "N H W"], gt_depth: Float[Tensor, "N H W"]) -> DepthScores:
    """AbsRel and delta1 of relative disparity predictions against ground-truth z-depth (0 = background)."""
    if pred_disp.shape != gt_depth.shape:
        raise ValueError(f"prediction {tuple(pred_disp.shape)} and ground truth {tuple(gt_depth.shape)} differ")
    pred_disp, gt_depth = pred_disp.double(), gt_depth.double()
    mask = (gt_depth > 0) & torch.isfinite(pred_disp)
    gt_disp = torch.where(mask, 1.0 / gt_depth.clamp_min(1e-12), torch.zeros_like(gt_depth))
    aligned = align_disparity(torch.where(mask, pred_disp, torch.zeros_like(pred_disp)), gt_disp, mask)
    z_max = gt_depth.flatten(1).amax(dim=1).clamp_min(1e-12)
    aligned = torch.maximum(aligned, (1.0 / (DEPTH_CAP_FACTOR * z_max))[:, None, None])
    pred_depth = 1.0 / aligned
    safe_gt = torch.where(mask, gt_depth, torch.ones_like(gt_depth))
    rel = ((pred_depth - safe_gt).abs() / safe_gt) * mask
    ratio = torch.maximum(pred_depth / safe_gt, safe_gt / pred_depth)
    hit = (ratio < DELTA_THRESHOLD) & mask
    count = mask.flatten(1).sum(dim=1)
    denom = count.clamp_min(1).double()
    return DepthScores(abs_rel=(rel.flatten(1).sum(1) / denom).float(),
                       delta1=(hit.flatten(1).sum(1) / denom).float(), valid=count > 0)
