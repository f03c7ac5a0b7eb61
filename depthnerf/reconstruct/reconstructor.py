"""Single-photo reconstruction: the :class:`Reconstructor` API behind ``depthnerf reconstruct``.

Photo reading, masking and framing: :mod:`depthnerf.reconstruct.photo`.
Camera
    The input camera sits at ``radius`` from the origin at ``elevation`` degrees (azimuth 0), looking at the origin
    (:mod:`depthnerf.reconstruct.orbit`); focal length in pixels of the category's 128 px release frame (SRN: 131.25),
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
    frustum box with the run's z-range, at the auto level of :mod:`depthnerf.render.mesh` unless fixed) with vertex colours = the fine
    network's rgb at each vertex seen along the input camera's ray through it, and a point cloud = the rendered
    depth of every orbit view unprojected where opacity > :data:`POINT_OPACITY` (at most ``max_points`` points,
    an even subsample). :meth:`Reconstructor.save` writes them (:mod:`depthnerf.reconstruct.exports`).
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import trimesh
from jaxtyping import Float
from tqdm import tqdm

from depthnerf.data.cameras import Intrinsics
from depthnerf.data.srn import ObjectRecord, ObjectViews, category_defaults, mask_bboxes
from depthnerf.depth.estimators import make_estimator
from depthnerf.errors import DepthnerfError
from depthnerf.eval.pretrained import Pretrained, load_pretrained
from depthnerf.model.conditioning import source_views
from depthnerf.reconstruct.orbit import orbit_points, orbit_poses, srn_intrinsics
from depthnerf.reconstruct.photo import DEFAULT_FILL, FILL, ImageLike, PreparedImage, prepare_photo
from depthnerf.render.mesh import AUTO_LEVEL, MeshConfig, input_camera_mesh
from depthnerf.render.views import render_poses
from depthnerf.train.config import z_range

POINT_OPACITY = 0.5
"""Rendered pixels with more than this opacity go into the point cloud."""
RELEASE_SIZE = 128
"""Frame size ``--focal`` refers to when the category is not a known SRN one (SRN images are 128 px)."""
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
    """Density level of the mesh surface, or ``"auto"`` (see :mod:`depthnerf.render.mesh`)."""
    max_points: int = 200_000
    """Largest point-cloud size."""
    chunk: int = 4096
    """Rays per render pass."""
    progress: bool = False
    """Show a progress bar (stderr)."""


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
        pixel_center = train.data.pixel_center  # the photo's SRN-style intrinsics read as training read the data
        intr = srn_intrinsics(focal, image_size, res, pixel_center)
        render_res = cfg.render_resolution or res
        render_intr = srn_intrinsics(focal, image_size, render_res, pixel_center)
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
        out = render_poses(model, enc, poses, render_intr, near, far, train.render, cfg.chunk, self.device,
                           bar.update)
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
        from depthnerf.reconstruct.exports import save_reconstruction

        pre = self.pretrained
        provenance = {"checkpoint": str(pre.path.resolve()), "checkpoint_sha256": pre.sha256,
                      "checkpoint_step": pre.step, "preset": pre.config.preset}
        return save_reconstruction(result, Path(out_dir), provenance)
