"""The framing rule: a photo's object recentred and scaled to the fill of a model's training images.

``reconstruct`` frames every photo by it (:func:`depthnerf.reconstruct.photo.prepare_photo`), and ``depthnerf
fit-facing --inputs photo`` frames dataset views by it so that a facing head learns from what a photo looks like to
the model. It lives with the data because it only reads pixels and a mask.

``framing="auto"``: a square crop centred on the mask's bounding box, of side ``max(box width, box height) /
fill``, padded with white where it leaves the image, then resampled to the model's training resolution (area
averaging, bilinear when enlarging; mask = any area coverage, as :func:`depthnerf.data.srn.load_object`
resizes masks; a square wider than :data:`MAX_CANVAS` px, which a small ``fill`` asks for, is built at a
reduced scale, the photo's part of it area-resampled first, so memory stays bounded at any fill). ``fill`` is
the fraction of the frame the object's longer box side takes in training images: :func:`category_fill`, the
fill of the synthetic benchmark's framing the checkpoint was trained on (``Framing.fill`` in
:mod:`depthnerf.data.synth.framing`, measured by ``scripts/measure_fill.py``), :data:`DEFAULT_FILL` for other
categories.
``framing="keep"`` only pads the image to a square (centred) and resamples it, for images already framed like
the training data (e.g. an SRN view at the training camera).
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from depthnerf.data.cameras import Intrinsics
from depthnerf.data.srn import mask_bboxes
from depthnerf.data.synth.framing import DEFAULT_FRAMING, get_framing
from depthnerf.errors import DepthnerfError

MAX_CANVAS = 4096
"""Widest square the framing builds before resampling (a smaller ``fill`` frames at a reduced scale first)."""
DEFAULT_FILL = 0.62
"""``fill`` for other categories."""


def square_crop(mask: np.ndarray, framing: str, fill: float) -> tuple[int, int, int]:
    """``(left, top, side)`` in pixels of the square the framing rule crops from an image with ``mask`` (module
    docstring); it may reach past the image, where :func:`frame_photo` pads with white."""
    height, width = mask.shape
    if framing == "auto":
        if not 0 < fill <= 1:
            raise DepthnerfError(f"--fill must be in (0, 1], got {fill}")
        x0, y0, x1, y1 = mask_bboxes(torch.from_numpy(mask)[None])[0].tolist()
        side = max(x1 - x0 + 1, y1 - y0 + 1) / fill
        cx, cy = (x0 + x1 + 1) / 2, (y0 + y1 + 1) / 2
    elif framing == "keep":
        side, cx, cy = max(height, width), width / 2, height / 2
    else:
        raise DepthnerfError(f"framing must be 'auto' or 'keep', got {framing!r}")
    side_px = max(1, math.ceil(side))
    return round(cx - side_px / 2), round(cy - side_px / 2), side_px


def framed_intrinsics(intr: Intrinsics, crop: tuple[int, int, int], resolution: int) -> Intrinsics:
    """The camera of the image :func:`frame_photo` makes from one taken with ``intr``: the :func:`square_crop`
    ``crop`` shifts the principal point by ``(left, top)``, the resampling to ``resolution`` scales it
    (:meth:`~depthnerf.data.cameras.Intrinsics.resized`)."""
    left, top, side = crop
    return Intrinsics(focal=intr.focal, cx=intr.cx - left, cy=intr.cy - top, height=side,
                      width=side).resized(resolution, resolution)


def frame_photo(rgb: np.ndarray, alpha: np.ndarray | None, mask: np.ndarray, resolution: int, framing: str,
                fill: float, notes: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """Composite on white, crop/pad square by the framing rule (:func:`square_crop`) and resample to
    ``resolution``."""
    if alpha is not None:
        rgb = rgb * alpha[..., None] + (1.0 - alpha[..., None])
    rgb = np.where(mask[..., None], rgb, 1.0).astype(np.float32)
    height, width = mask.shape
    left, top, side_px = square_crop(mask, framing, fill)
    sx0, sy0 = max(0, left), max(0, top)
    sx1, sy1 = min(width, left + side_px), min(height, top + side_px)
    notes.append(f"framing {framing}: square crop x {left}..{left + side_px}, y {top}..{top + side_px} of the "
                 f"{width}x{height} image, resampled to {resolution}x{resolution}")
    scale = min(1.0, MAX_CANVAS / side_px)  # a small fill pads a huge square: built at most MAX_CANVAS px wide
    n = max(1, round(side_px * scale))
    canvas = np.ones((n, n, 3), dtype=np.float32)
    cmask = np.zeros((n, n), dtype=bool)
    part, part_mask = rgb[sy0:sy1, sx0:sx1], mask[sy0:sy1, sx0:sx1]
    px, py = round((sx0 - left) * scale), round((sy0 - top) * scale)
    if scale < 1.0:  # the photo's part of the square, area-resampled to the canvas's scale
        pw, ph = min(max(1, round((sx1 - sx0) * scale)), n - px), min(max(1, round((sy1 - sy0) * scale)), n - py)
        part = F.interpolate(torch.from_numpy(np.ascontiguousarray(part)).permute(2, 0, 1)[None], size=(ph, pw),
                             mode="area")[0].permute(1, 2, 0).numpy()
        part_mask = (F.interpolate(torch.from_numpy(part_mask)[None, None].float(), size=(ph, pw),
                                   mode="area")[0, 0] > 0).numpy()
    canvas[py:py + part.shape[0], px:px + part.shape[1]] = part
    cmask[py:py + part.shape[0], px:px + part.shape[1]] = part_mask
    img_t = torch.from_numpy(canvas).permute(2, 0, 1)[None]
    size = (resolution, resolution)
    img_t = (F.interpolate(img_t, size=size, mode="area") if n >= resolution
             else F.interpolate(img_t, size=size, mode="bilinear", align_corners=False)).clamp(0, 1)
    cover = F.interpolate(torch.from_numpy(cmask)[None, None].float(), size=size, mode="area")
    return img_t[0].permute(1, 2, 0).numpy(), (cover[0, 0] > 0).numpy()


def category_fill(category: str, framing: str = DEFAULT_FRAMING) -> float:
    """The fill a model of ``category`` trained on ``framing``'s data was trained at (else :data:`DEFAULT_FILL`)."""
    return get_framing(framing).fill(category, DEFAULT_FILL)
