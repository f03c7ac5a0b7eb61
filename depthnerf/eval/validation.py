"""Validation during training: PSNR/SSIM on a few fixed val objects, rendered from the protocol's input view (or
the views ``--log.val_input_views`` names).

``depthnerf train`` passes :func:`validate` to the training loop (:class:`depthnerf.train.validator.Validator`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from depthnerf.data.protocol import protocol_views, validation_targets
from depthnerf.data.srn import ObjectRecord, load_object
from depthnerf.depth.prior import DatasetViews, PriorSource
from depthnerf.eval.metrics import object_metrics
from depthnerf.model.conditioning import condition
from depthnerf.model.pixelnerf import FieldRuntime, PixelNeRF
from depthnerf.pretrained.spec import InferenceSpec
from depthnerf.render.precision import inference_policy
from depthnerf.render.views import render_views


@dataclass
class ValidationResult:
    """Mean metrics over the validation objects and images of the first one for TensorBoard."""

    psnr: float
    """Mean over objects of the per-object mean PSNR (dB)."""
    ssim: float
    """Mean over objects of the per-object mean SSIM."""
    images: dict[str, np.ndarray]
    """source, target, render, depth (rendered, normalised to [0, 1]) and prior (if any) of the first object."""


@torch.no_grad()
def validate(model: PixelNeRF, records: Sequence[ObjectRecord], prior_source: PriorSource, views: Sequence[int],
             spec: InferenceSpec, chunk: int, device: torch.device,
             progress: Callable[[int], Any] | None = None,
             symmetry_plane: Sequence[float] | None = None,
             inputs: Sequence[int] | None = None) -> ValidationResult:
    """Render ``views`` of each record from its input views (``inputs``, the first the primary; None: the
    protocol's one) and score them against the ground truth (``progress(1)`` after each record);
    ``symmetry_plane``: the objects' mirror plane (mirror models)."""
    modes = [(module, module.training) for module in model.modules()]  # each restored (frozen modules stay in eval)
    model.eval()
    # the device's field point chunk (on the CPU larger than the config's, which is slower there); the precision
    # stays the model's: validation scores the fp32 model on every device
    runtime = FieldRuntime(chunk_points=inference_policy(device, fp32=True).point_chunk)
    scores, images = [], {}
    resolution, (near, far), render_cfg = spec.resolution, spec.z_range, spec.render
    try:
        for i, record in enumerate(records):
            srcs = protocol_views(record.num_views, inputs=inputs).input_views
            targets = validation_targets(views, record.num_views, inputs)
            obj = load_object(record, [*srcs, *targets], resolution=resolution, pixel_center=spec.pixel_center)
            n = len(srcs)
            cond = condition(prior_source, obj.images[:n], obj.masks[:n], obj.poses[:n], obj.intrinsics, device,
                             where=DatasetViews(record, srcs), symmetry_plane=symmetry_plane)
            disparity = cond.disparity
            enc = model.encode(cond.inputs)
            out = render_views(model.field(enc, "coarse", runtime), model.field(enc, "fine", runtime),
                               obj.poses[n:].to(device), obj.intrinsics, near, far, render_cfg, chunk=chunk)
            preds = out.rgb.cpu().numpy()
            gts = obj.images[n:].permute(0, 2, 3, 1).numpy()
            scores.append(object_metrics(record.object_id, list(preds), list(gts)))
            if i == 0:
                distance = out.distance[0].cpu().numpy()
                images = {"source": obj.images[0].permute(1, 2, 0).numpy(), "target": gts[0], "render": preds[0],
                          "depth": (far - distance) / (far - near)}
                if disparity is not None:
                    d = disparity[0].numpy()
                    images["prior"] = (d - d.min()) / max(float(d.max() - d.min()), 1e-8)
            if progress is not None:
                progress(1)
    finally:
        for module, mode in modes:
            module.training = mode
    return ValidationResult(psnr=float(np.mean([s.psnr for s in scores])),
                            ssim=float(np.mean([s.ssim for s in scores])), images=images)
