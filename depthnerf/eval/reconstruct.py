"""Single-photo reconstruction: the :class:`Reconstructor` API behind ``depthnerf reconstruct``.

Input photo (assumption: ONE object, roughly centred, on a plain background)
    Any image Pillow reads; grayscale is replicated to RGB (noted); sides below :data:`MIN_SIDE` px are an error;
    images larger than :data:`MAX_SIDE` px are first downscaled (box filter) so the longer side is ``MAX_SIDE``
    (noted). Mask, in order: the given mask (non-zero = object, same size as the image); else the alpha channel
    (``alpha > 0.5``) when the image has a non-opaque alpha; else the *background colour* = the per-channel median
    of the image border (a ring ``max(1, 2%)`` of the shorter side wide) and object = pixels whose largest channel
    difference from it exceeds :data:`BACKGROUND_TOLERANCE` (0.1, i.e. ~26 of 255 levels). Background pixels are
    then set to white (alpha is composited on white), as in the SRN training images.
Framing rule (``framing="auto"``)
    A square crop centred on the mask's bounding box, of side ``max(box width, box height) / fill``, padded with
    white where it leaves the image, then resampled to the model's training resolution (area averaging, bilinear
    when enlarging; mask = any area coverage, as :func:`depthnerf.data.srn.load_object` resizes masks). ``fill`` is the fraction of the
    frame the object's longer box side takes in training images: :data:`FILL` per category (measured as the median
    over 300 masks of 6 synthetic train objects per category at 128 px: cars 0.656, chairs 0.594), 0.62 otherwise.
    ``framing="keep"`` only pads the image to a square (centred) and resamples it, for images already framed like
    the training data (e.g. an SRN view at the training camera).
Camera
    The input camera sits at ``radius`` from the origin at ``elevation`` degrees (azimuth 0), looking at the origin
    (:mod:`depthnerf.eval.orbit`); focal length in pixels of the category's 128 px release frame (SRN: 131.25),
    rescaled to the working resolution. Defaults: the checkpoint's training category
    (:func:`~depthnerf.data.srn.category_defaults`), elevation 20 degrees; a category without defaults needs both
    ``radius`` and ``focal`` (then in pixels of a 128 px frame).
Depth prior (depth-aware checkpoints)
    The checkpoint's estimator (``make_estimator``) on the prepared image at the training resolution (as the cache
    is computed), normalised over the mask by :func:`depthnerf.model.conditioning.source_views`, as in training.
    ``oracle`` needs ground-truth depth, impossible for a photo: an error suggesting ``depth_estimator="bundled"``.
Outputs
    N views on the orbit through the input camera (rendered at ``render_resolution``, default the training one),
    their depth (ray distance, opacity-normalised) and opacity, a mesh (marching cubes over the input camera's
    frustum box with the run's z-range, at the auto level of :mod:`depthnerf.eval.mesh` unless fixed) with vertex colours = the fine
    network's rgb at each vertex seen along the input camera's ray through it, and a point cloud = the rendered
    depth of every orbit view unprojected where opacity > :data:`POINT_OPACITY` (at most ``max_points`` points,
    an even subsample). :meth:`Reconstructor.save` writes them (:mod:`depthnerf.eval.exports`).
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
import trimesh
from jaxtyping import Bool, Float
from PIL import Image
from tqdm import tqdm

from depthnerf.data.cameras import Intrinsics
from depthnerf.data.srn import ObjectRecord, ObjectViews, category_defaults, mask_bboxes
from depthnerf.depth.estimators import make_estimator
from depthnerf.errors import DepthnerfError
from depthnerf.eval.mesh import AUTO_LEVEL, MeshConfig
from depthnerf.eval.orbit import (
    input_camera_mesh,
    orbit_points,
    orbit_poses,
    render_poses,
    srn_intrinsics,
)
from depthnerf.eval.pretrained import Pretrained, load_pretrained
from depthnerf.model.conditioning import source_views
from depthnerf.train.config import z_range

MIN_SIDE = 16
"""Smallest accepted image side (pixels)."""
MAX_SIDE = 1024
"""Longer image sides are downscaled to this first."""
BACKGROUND_TOLERANCE = 0.1
"""Largest per-channel difference from the border colour that still counts as background (in [0, 1])."""
ALPHA_THRESHOLD = 0.5
"""Alpha above this is object."""
FILL = {"cars": 0.65, "chairs": 0.6}
"""Fraction of the frame the object's longer bounding-box side takes in training images, per category."""
DEFAULT_FILL = 0.62
"""``fill`` for other categories."""
POINT_OPACITY = 0.5
"""Rendered pixels with more than this opacity go into the point cloud."""
RELEASE_SIZE = 128
"""Frame size ``--focal`` refers to when the category is not a known SRN one (SRN images are 128 px)."""
ImageLike = str | Path | np.ndarray | Image.Image


@dataclass(frozen=True)
class ReconstructConfig:
    """How a photo is reconstructed (None = the checkpoint's training category / resolution)."""

    views: int = 36
    """Novel views on the orbit (view 0 = the input camera)."""
    elevation: float = 20.0
    """Elevation of the input camera (and of the orbit), degrees."""
    radius: float | None = None
    """Camera distance from the object centre; None = the category's."""
    focal: float | None = None
    """Focal length in pixels of the category's 128 px frame; None = the category's (SRN 131.25)."""
    framing: str = "auto"
    """``auto`` (crop around the object to the training fill) or ``keep`` (pad to square only)."""
    fill: float | None = None
    """Fraction of the frame the object's longer side takes with ``auto``; None = :data:`FILL` of the category."""
    render_resolution: int | None = None
    """Side of the rendered views; None = the training resolution."""
    mesh_resolution: int = 128
    """Marching-cubes samples along the frustum box's longest side (0 = no mesh)."""
    mesh_threshold: float | str = AUTO_LEVEL
    """Density level of the mesh surface, or ``"auto"`` (see :mod:`depthnerf.eval.mesh`)."""
    max_points: int = 200_000
    """Largest point-cloud size."""
    chunk: int = 4096
    """Rays per render pass."""
    progress: bool = False
    """Show a progress bar (stderr)."""


@dataclass
class PreparedImage:
    """The photo as the model sees it."""

    image: Float[np.ndarray, "H W 3"]
    """RGB in [0, 1] on white, square, at the training resolution."""
    mask: Bool[np.ndarray, "H W"]
    """Object pixels."""
    notes: list[str]
    """What was done to the input (grayscale, downscaled, mask source, crop)."""
    source_size: tuple[int, int]
    """(height, width) of the file as read."""


@dataclass
class Reconstruction:
    """Everything reconstructed from one photo (arrays on the CPU)."""

    input: PreparedImage
    """The prepared input view."""
    depth_prior: Float[np.ndarray, "H W"] | None
    """Raw relative disparity from the estimator (None for the baseline)."""
    prior_normalized: Float[np.ndarray, "H W"] | None
    """What the encoder saw: normalised disparity (foreground [-4, 4], background -5)."""
    poses: Float[np.ndarray, "N 4 4"]
    """Camera-to-world poses of the orbit views (OpenCV axes); pose 0 is the input camera."""
    intrinsics: Intrinsics
    """Intrinsics of the rendered views."""
    views: Float[np.ndarray, "N H W 3"]
    """Rendered RGB in [0, 1]."""
    depths: Float[np.ndarray, "N H W"]
    """Rendered ray distance of the visible surface (``far`` where nothing was hit)."""
    opacity: Float[np.ndarray, "N H W"]
    """Rendered opacity."""
    mesh: trimesh.Trimesh
    """World-frame mesh with vertex colours (empty when the density never reached the level or meshing was off)."""
    points: Float[np.ndarray, "P 3"]
    """World-frame point cloud."""
    point_colors: Float[np.ndarray, "P 3"]
    """Point colours in [0, 1]."""
    settings: dict[str, Any]
    """Camera, framing, depth prior and mesh settings actually used."""
    timings: dict[str, float] = field(default_factory=dict)
    """Seconds per stage."""


def _to_float(arr: np.ndarray) -> np.ndarray:
    """Float32 ``H x W x C`` in [0, 1] from 8-bit, 16-bit or float pixels."""
    arr = arr[..., None] if arr.ndim == 2 else arr
    if arr.dtype == np.uint8:
        return arr.astype(np.float32) / 255.0
    if arr.dtype.kind in "iu":
        return arr.astype(np.float32) / 65535.0
    return np.clip(arr.astype(np.float32), 0.0, 1.0)


def _open(source: str | Path | Image.Image, name: str) -> Image.Image:
    try:
        im = source if isinstance(source, Image.Image) else Image.open(source)
        im.load()
    except FileNotFoundError:
        raise DepthnerfError(f"{name}: image file not found") from None
    except (OSError, ValueError, Image.DecompressionBombError) as err:
        raise DepthnerfError(f"{name}: unreadable image ({err})") from None
    if im.mode in ("P", "PA", "CMYK", "YCbCr", "HSV", "LAB", "RGBa", "La"):
        return im.convert("RGBA")
    if im.mode == "1" or im.mode.startswith("I;16"):
        return im.convert("L" if im.mode == "1" else "I")
    return im


def read_photo(source: ImageLike, notes: list[str]) -> tuple[np.ndarray, np.ndarray | None, tuple[int, int]]:
    """``(rgb [H, W, 3], alpha [H, W] or None, (H, W) as read)`` in [0, 1], grayscale replicated, images
    larger than :data:`MAX_SIDE` downscaled (see the module docstring); ``notes`` collects what was done."""
    name = str(source) if isinstance(source, str | Path) else "image"
    im = None if isinstance(source, np.ndarray) else _open(source, name)
    if im is None:
        arr = np.asarray(source)
        if arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[-1] not in (1, 2, 3, 4)):
            raise DepthnerfError(f"image: expected an H x W (x 1|2|3|4) array, got shape {arr.shape}")
        size = arr.shape[:2]
    else:
        size = (im.height, im.width)
    if min(size) < MIN_SIDE:
        raise DepthnerfError(f"{name}: image is {size[1]}x{size[0]} px; at least {MIN_SIDE} px per side are needed")
    small = size
    if max(size) > MAX_SIDE:
        scale = MAX_SIDE / max(size)
        small = (max(MIN_SIDE, round(size[0] * scale)), max(MIN_SIDE, round(size[1] * scale)))
        notes.append(f"downscaled from {size[1]}x{size[0]} to {small[1]}x{small[0]} (box filter) first")
        if im is not None:
            im = im.resize((small[1], small[0]), Image.Resampling.BOX)
    if im is not None:
        img = _to_float(np.asarray(im))
    else:
        img = _to_float(arr)
        if small != size:
            t = torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1)[None]
            img = F.interpolate(t, size=small, mode="area")[0].permute(1, 2, 0).numpy()
    if img.shape[-1] in (1, 2):
        notes.append("grayscale image: replicated to RGB")
        img = np.concatenate([np.repeat(img[..., :1], 3, axis=-1), img[..., 1:]], axis=-1)
    alpha = img[..., 3] if img.shape[-1] == 4 else None
    if alpha is not None and alpha.min() >= 1.0:
        alpha = None
    return np.ascontiguousarray(img[..., :3]), alpha, size


def photo_mask(rgb: np.ndarray, alpha: np.ndarray | None, mask: ImageLike | None, notes: list[str],
               name: str = "image", source_size: tuple[int, int] | None = None) -> np.ndarray:
    """The object mask by the rule of the module docstring (given mask, alpha, or border background colour).

    A given mask must have the image's size as read (``source_size``); it is downscaled with the image.
    """
    height, width = rgb.shape[:2]
    if mask is not None:
        where = "mask" if isinstance(mask, np.ndarray | Image.Image) else str(mask)
        try:
            im = Image.fromarray(np.asarray(mask)) if isinstance(mask, np.ndarray) else (
                mask if isinstance(mask, Image.Image) else Image.open(mask))
            im = im.convert("L")
        except FileNotFoundError:
            raise DepthnerfError(f"{where}: mask file not found") from None
        except (OSError, ValueError, TypeError) as err:
            raise DepthnerfError(f"{where}: unreadable mask ({err})") from None
        if source_size is not None and (im.height, im.width) == source_size != (height, width):
            im = im.resize((width, height), Image.Resampling.BOX)
        if (im.height, im.width) != (height, width):
            raise DepthnerfError(f"{where}: mask is {im.width}x{im.height} but the image is "
                                 f"{(source_size or (height, width))[1]}x{(source_size or (height, width))[0]}")
        notes.append("mask: given (value > 127 of 255 = object)")
        out = np.asarray(im) > 127
    elif alpha is not None:
        notes.append(f"mask: alpha > {ALPHA_THRESHOLD}")
        out = alpha > ALPHA_THRESHOLD
    else:
        ring = max(1, round(0.02 * min(height, width)))
        border = np.concatenate([rgb[:ring].reshape(-1, 3), rgb[-ring:].reshape(-1, 3),
                                 rgb[:, :ring].reshape(-1, 3), rgb[:, -ring:].reshape(-1, 3)])
        bg = np.median(border, axis=0)
        out = np.abs(rgb - bg).max(axis=-1) > BACKGROUND_TOLERANCE
        notes.append(f"mask: pixels differing from the border colour {np.round(bg * 255).astype(int).tolist()} by "
                     f"more than {BACKGROUND_TOLERANCE}")
    if not out.any():
        raise DepthnerfError(f"{name}: no object found (the mask is empty); pass a mask (--mask)")
    return out


def frame_photo(rgb: np.ndarray, alpha: np.ndarray | None, mask: np.ndarray, resolution: int, framing: str,
                fill: float, notes: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """Composite on white, crop/pad square by the framing rule and resample to ``resolution``."""
    if alpha is not None:
        rgb = rgb * alpha[..., None] + (1.0 - alpha[..., None])
    rgb = np.where(mask[..., None], rgb, 1.0).astype(np.float32)
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
    left, top = round(cx - side_px / 2), round(cy - side_px / 2)
    canvas = np.ones((side_px, side_px, 3), dtype=np.float32)
    cmask = np.zeros((side_px, side_px), dtype=bool)
    sx0, sy0 = max(0, left), max(0, top)
    sx1, sy1 = min(width, left + side_px), min(height, top + side_px)
    canvas[sy0 - top:sy1 - top, sx0 - left:sx1 - left] = rgb[sy0:sy1, sx0:sx1]
    cmask[sy0 - top:sy1 - top, sx0 - left:sx1 - left] = mask[sy0:sy1, sx0:sx1]
    notes.append(f"framing {framing}: square crop x {left}..{left + side_px}, y {top}..{top + side_px} of the "
                 f"{width}x{height} image, resampled to {resolution}x{resolution}")
    img_t = torch.from_numpy(canvas).permute(2, 0, 1)[None]
    size = (resolution, resolution)
    img_t = (F.interpolate(img_t, size=size, mode="area") if side_px >= resolution
             else F.interpolate(img_t, size=size, mode="bilinear", align_corners=False)).clamp(0, 1)
    cover = F.interpolate(torch.from_numpy(cmask)[None, None].float(), size=size, mode="area")
    return img_t[0].permute(1, 2, 0).numpy(), (cover[0, 0] > 0).numpy()


def prepare_photo(image: ImageLike, mask: ImageLike | None, resolution: int, framing: str = "auto",
                  fill: float = DEFAULT_FILL) -> PreparedImage:
    """Read, mask and frame a photo for a model trained at ``resolution`` (module docstring)."""
    notes: list[str] = []
    rgb, alpha, size = read_photo(image, notes)
    name = str(image) if isinstance(image, str | Path) else "image"
    m = photo_mask(rgb, alpha, mask, notes, name, size)
    img, m_small = frame_photo(rgb, alpha, m, resolution, framing, fill, notes)
    return PreparedImage(image=img, mask=m_small, notes=notes, source_size=size)


class Reconstructor:
    """A loaded checkpoint that turns one photo into novel views, depths, a mesh and a point cloud."""

    def __init__(self, pretrained: Pretrained, device: torch.device | str = "cpu", depth_estimator: str | None = None,
                 depth_checkpoint: str | None = None) -> None:
        self.pretrained = pretrained
        self.device = torch.device(device)
        cfg = pretrained.config
        self.estimator_name = depth_estimator or cfg.prior.estimator
        if cfg.model.encoder.use_depth and self.estimator_name == "none":
            raise DepthnerfError(f"{pretrained.path}: depth-aware checkpoint needs a depth estimator, not 'none'")
        if self.estimator_name == "oracle" and cfg.model.encoder.use_depth:
            raise DepthnerfError(f"{pretrained.path}: trained with the 'oracle' prior (ground-truth depth), which a "
                                 "photo does not have; use --depth-estimator bundled (or depth-anything-v2)")
        ckpt = depth_checkpoint if depth_checkpoint is not None else (
            cfg.prior.checkpoint if self.estimator_name == cfg.prior.estimator else None)
        self.estimator_checkpoint = ckpt
        self.estimator = make_estimator(self.estimator_name, ckpt, device=str(self.device)) \
            if cfg.model.encoder.use_depth else None

    @classmethod
    def from_pretrained(cls, path_or_name: str | Path, device: torch.device | str = "cpu",
                        depth_estimator: str | None = None, depth_checkpoint: str | None = None) -> Reconstructor:
        """Load a shipped name, weights file, checkpoint folder or run folder (``load_pretrained``)."""
        return cls(load_pretrained(path_or_name, device), device, depth_estimator, depth_checkpoint)

    @torch.no_grad()
    def reconstruct(self, image: ImageLike, mask: ImageLike | None = None, views: int | None = None,
                    config: ReconstructConfig | None = None) -> Reconstruction:
        """Reconstruct one photo (see the module docstring); ``views`` (default 36) overrides ``config.views``."""
        cfg = config or ReconstructConfig()
        views = cfg.views if views is None else views
        train, model = self.pretrained.config, self.pretrained.model
        times: dict[str, float] = {}
        t = time.perf_counter()
        res = train.data.resolution
        if cfg.radius is not None and cfg.focal is not None:
            radius, focal, image_size = cfg.radius, cfg.focal, RELEASE_SIZE
        else:
            cat = category_defaults(train.data.category)  # unknown category: an error asking for both
            radius, focal, image_size = cfg.radius or cat.camera_radius, cfg.focal or cat.focal, cat.image_size
        fill = cfg.fill if cfg.fill is not None else FILL.get(train.data.category, DEFAULT_FILL)
        prepared = prepare_photo(image, mask, res, cfg.framing, fill)
        times["prepare_s"] = time.perf_counter() - t
        poses = orbit_poses(radius, cfg.elevation, views)
        intr = srn_intrinsics(focal, image_size, res)
        render_res = cfg.render_resolution or res
        render_intr = srn_intrinsics(focal, image_size, render_res)
        near, far = z_range(train)
        bar = tqdm(total=views + 2, desc="reconstruct", unit="step", file=sys.stderr, disable=not cfg.progress)
        t = time.perf_counter()
        img_t = torch.from_numpy(prepared.image).permute(2, 0, 1)[None].contiguous()
        mask_t = torch.from_numpy(prepared.mask)[None]
        disp = None
        if self.estimator is not None:
            disp = self.estimator.predict(img_t).float()
        record = ObjectRecord(category=train.data.category, split="photo", object_id="photo", path=Path("."),
                              view_names=("input",), intrinsics=intr, has_depth=False, has_mask=True, mesh_path=None)
        obj = ObjectViews(record=record, view_indices=torch.zeros(1, dtype=torch.long), images=img_t,
                          poses=poses[:1], intrinsics=intr, masks=mask_t, bboxes=mask_bboxes(mask_t), depths=None)
        src = source_views(obj, [0], disp, self.device)
        enc = model.encode(src)
        bar.update(1)
        times["encode_s"] = time.perf_counter() - t
        t = time.perf_counter()
        out = render_poses(model, enc, poses, render_intr, near, far, train, cfg.chunk, self.device, bar.update)
        times["render_s"] = time.perf_counter() - t
        t = time.perf_counter()
        mesh, level = trimesh.Trimesh(), None
        if cfg.mesh_resolution > 0:
            mesh, level = input_camera_mesh(model, enc, poses[0], intr, near, far,
                                            MeshConfig(cfg.mesh_resolution, cfg.mesh_threshold), self.device)
        bar.update(1)
        bar.close()
        times["mesh_s"] = time.perf_counter() - t
        points, colors = orbit_points(out, poses, render_intr, POINT_OPACITY, cfg.max_points)
        settings = {"radius": radius, "elevation": cfg.elevation, "focal": focal, "focal_frame": image_size,
                    "resolution": res, "render_resolution": render_res, "views": views, "z_range": [near, far],
                    "framing": cfg.framing, "fill": fill, "category": train.data.category,
                    "depth_estimator": self.estimator_name if self.estimator is not None else "none",
                    "depth_checkpoint": self.estimator_checkpoint, "mesh_resolution": cfg.mesh_resolution,
                    "mesh_threshold": cfg.mesh_threshold, "mesh_level": level and level.level,
                    "mesh_level_rule": level and level.describe(), "point_opacity": POINT_OPACITY,
                    "mesh_colors": "fine-network rgb at each vertex seen along the input camera's ray"}
        prior_n = src.prior[0, 0, 0].cpu().numpy() if src.prior is not None else None
        return Reconstruction(
            input=prepared, depth_prior=None if disp is None else disp[0].numpy(), prior_normalized=prior_n,
            poses=poses.numpy(), intrinsics=render_intr, views=out.rgb.numpy(), depths=out.depth.numpy(),
            opacity=out.opacity.numpy(), mesh=mesh, points=points.astype(np.float32),
            point_colors=colors.astype(np.float32), settings=settings, timings=times)

    def save(self, result: Reconstruction, out_dir: str | Path) -> dict[str, Any]:
        """Write every output into ``out_dir`` and return the manifest (also ``out_dir/manifest.json``)."""
        from depthnerf.eval.exports import save_reconstruction

        pre = self.pretrained
        provenance = {"checkpoint": str(pre.path.resolve()), "checkpoint_sha256": pre.sha256,
                      "checkpoint_step": pre.step, "preset": pre.config.preset}
        return save_reconstruction(result, Path(out_dir), provenance)
