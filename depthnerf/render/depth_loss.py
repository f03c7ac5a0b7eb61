"""Closed-form scale/shift fitting and the scale-and-shift-invariant (SSI) depth loss (beyond the paper).

Units: the renderer's depth is ray distance ``t``; a monocular prior is relative *disparity* of z-depth
(``a / z + b`` for unknown ``a > 0, b``). The loss therefore converts the rendered depth to z (``z = t cos theta``,
``cos theta`` = camera-frame z of the unit ray direction, see ``rays.camera_z_of_directions``) and then to
disparity ``1 / z`` before comparing. Which view: the prior must be the prior of the view the rays belong to. In
training the rays are random pixels of a *target* view, while the network's input prior is the *source* view's,
so the training loop must pass the TARGET view's prior sampled at the ray pixels (``TrainBatch.target_prior``).
"""

from __future__ import annotations

import torch
from jaxtyping import Bool, Float
from torch import Tensor

from depthnerf.depth.metrics import fit_scale_shift

MIN_PIXELS = 3
"""Images with fewer foreground rays than this have no meaningful affine fit and contribute nothing."""


def ssi_depth_loss(depth: Float[Tensor, "B R"], prior_disp: Float[Tensor, "B R"], mask: Bool[Tensor, "B R"], *,
                   dirs_cam_z: Float[Tensor, "B R"] | None = None, min_depth: float = 1e-2,
                   opacity: Float[Tensor, "B R"] | None = None, min_opacity: float = 0.0) -> Float[Tensor, ""]:
    """Scale-and-shift-invariant L2 loss between rendered depth and a relative-disparity prior, on foreground.

    Per image (row): ``d = 1 / max(z, min_depth)`` with ``z = depth * dirs_cam_z`` if ``dirs_cam_z`` is given
    (``depth`` is ray distance ``t``), else ``z = depth`` (already z-depth). Fit ``s, b`` so that ``s p + b ~ d``
    (prior ``p`` mapped onto the rendered disparity, least squares over the mask), residual ``r = d - (s p + b)``,
    loss = mean over images with at least :data:`MIN_PIXELS` foreground rays of ``mean_mask(r^2)``; 0 (with a
    graph) if there is none.

    Properties: exactly invariant to any affine change ``a p + c`` of the prior (``a != 0``; the sign of ``s`` is
    not constrained, so a depth-reversed render is not penalised: the photometric loss rules that out), 0 iff
    ``d`` is affine in ``p`` on the mask; units are (rendered disparity)^2, i.e. 1 / length^2. The fit is kept in the graph, but
    detaching it would give the same gradient: at the least-squares optimum ``dL/ds = dL/db = 0`` (envelope
    theorem), so ``dL/dd`` is the residual ``2 r / n``, the component of ``d`` the prior cannot explain. That
    gradient is orthogonal to ``{p, 1}``: the part of the rendered geometry the prior agrees with is never
    pushed towards flat.

    Rays the render leaves (nearly) empty: their opacity-normalised depth is undefined (0 on an empty ray, so
    disparity ``1 / min_depth``, an outlier that skews ``s, b`` and with them every other ray's residual) and its
    gradient grows as ``1 / opacity``. Pass the render's ``opacity`` (detached) and ``min_opacity``: rays with
    ``opacity < min_opacity`` leave the mask, so neither the fit nor the loss sees them.
    """
    per_image, usable = ssi_depth_loss_per_image(depth, prior_disp, mask, dirs_cam_z=dirs_cam_z,
                                                 min_depth=min_depth, opacity=opacity, min_opacity=min_opacity)
    # mean over the usable images, 0 (with a graph) when there is none; no host sync
    return per_image.sum() / usable.sum().clamp_min(1).to(per_image.dtype)


def ssi_depth_loss_per_image(depth: Float[Tensor, "B R"], prior_disp: Float[Tensor, "B R"],
                             mask: Bool[Tensor, "B R"], *, dirs_cam_z: Float[Tensor, "B R"] | None = None,
                             min_depth: float = 1e-2, opacity: Float[Tensor, "B R"] | None = None,
                             min_opacity: float = 0.0) -> tuple[Float[Tensor, " B"], Bool[Tensor, " B"]]:
    """The loss of :func:`ssi_depth_loss` per image (row), 0 for images with fewer than :data:`MIN_PIXELS`
    foreground rays, and which images are usable."""
    if not (depth.shape == prior_disp.shape == mask.shape):
        raise ValueError(f"ssi_depth_loss: shapes differ: depth {tuple(depth.shape)}, prior "
                         f"{tuple(prior_disp.shape)}, mask {tuple(mask.shape)}")
    z = depth * dirs_cam_z if dirs_cam_z is not None else depth
    disp = 1.0 / z.clamp_min(min_depth)
    mask = mask.bool() & torch.isfinite(prior_disp)
    if opacity is not None:
        mask = mask & (opacity.detach() >= min_opacity)
    s, b = fit_scale_shift(prior_disp, disp, mask)
    prior = torch.where(mask, prior_disp, torch.zeros_like(prior_disp))
    res = torch.where(mask, disp - (s[:, None] * prior + b[:, None]), torch.zeros_like(disp))
    count = mask.sum(-1)
    per_image = (res * res).sum(-1) / count.clamp_min(1).to(res.dtype)
    usable = count >= MIN_PIXELS
    return torch.where(usable, per_image, torch.zeros_like(per_image)), usable
