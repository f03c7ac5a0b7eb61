"""Single-photo reconstruction: the :class:`Reconstructor` API behind ``depthnerf reconstruct``.

Photo reading, masking and framing: :mod:`depthnerf.reconstruct.photo`; background removal for photos on a
cluttered background (``ReconstructConfig.background_removal`` / ``background_model``; loaded once per model and
kept): :mod:`depthnerf.reconstruct.background`.
Camera
    The input camera sits at ``radius`` from the origin at ``elevation`` degrees (azimuth 0), looking at the origin
    (:mod:`depthnerf.reconstruct.orbit`); focal length in pixels of the category's 128 px release frame (SRN: 131.25),
    rescaled to the working resolution. Defaults: the checkpoint's training category
    (:func:`~depthnerf.data.srn.category_defaults`), elevation 20 degrees; a category without defaults needs both
    ``radius`` and ``focal`` (then in pixels of a 128 px frame).
Session
    A Reconstructor is a thin user of an :class:`~depthnerf.infer.session.InferenceSession` on photos: the
    checkpoint's spec with the caller's overrides, the prior source, the device policy (bf16 and large ray chunks
    on CUDA, fp32, 4096 rays and 16,384 points on the CPU) and the guided setup are resolved there, once, for the
    CLI, the Python API, the demo and the app alike.
Depth prior (depth-aware checkpoints)
    The checkpoint's estimator run live on the prepared image at the training resolution (the session's
    :class:`~depthnerf.depth.prior.PriorSource`), normalised over the mask by the conditioning stage
    (:func:`depthnerf.model.conditioning.condition`), as in training. ``oracle`` needs ground-truth depth,
    impossible for a photo: an error suggesting ``--depth bundled``. Guided sampling (``--guided``, the session's
    or ``ReconstructConfig.guided`` per call): :mod:`depthnerf.render.source_guide`.
Outputs
    N views on the orbit through the input camera (rendered at ``render_resolution``, default the training one),
    their depth (ray distance, opacity-normalised) and opacity, a mesh (marching cubes over the input camera's
    frustum box with the run's z-range, at the ``local`` level of :mod:`depthnerf.render.mesh_level` unless set)
    with vertex colours by ``mesh_colors``' rule (:mod:`depthnerf.render.mesh_colors`; by default the photo's own
    where it sees the surface), and a point cloud = the rendered depth of every orbit view unprojected where
    opacity > :data:`POINT_OPACITY` (at most ``max_points`` points, an even subsample). :meth:`Reconstructor.save`
    writes them (:mod:`depthnerf.reconstruct.exports`).
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
import trimesh
from jaxtyping import Bool, Float
from tqdm import tqdm

from depthnerf.data.cameras import Intrinsics
from depthnerf.data.photo_framing import category_fill
from depthnerf.data.srn import CATEGORY_DEFAULTS, SRN_IMAGE_SIZE, category_defaults
from depthnerf.data.symmetry import facing_plane
from depthnerf.errors import DepthnerfError
from depthnerf.infer.facing import (
    AUTO,
    MIN_CONFIDENCE,
    FacingFit,
    check_min_confidence,
    fit_facing,
    with_plane,
)
from depthnerf.infer.session import EncodedView, InferenceSession, SessionOptions
from depthnerf.pretrained.load import Pretrained
from depthnerf.reconstruct.background import MODES, BackgroundRemover, choose_remover
from depthnerf.reconstruct.exports import save_reconstruction
from depthnerf.reconstruct.orbit import orbit_points, orbit_poses, srn_intrinsics
from depthnerf.reconstruct.photo import ImageLike, PreparedImage, prepare_photo
from depthnerf.reconstruct.result import Reconstruction
from depthnerf.render.config import GuidedConfig
from depthnerf.render.mesh import MeshConfig, check_mesh_keep, check_mesh_resolution, keep_pieces
from depthnerf.render.mesh_colors import check_color_rule, describe_colors
from depthnerf.render.mesh_level import LOCAL_LEVEL, parse_level
from depthnerf.render.photo_colors import PHOTO, PHOTO_FILL
from depthnerf.render.source_guide import as_guided
from depthnerf.render.views import ViewRenders

POINT_OPACITY = 0.5
"""Rendered pixels with more than this opacity go into the point cloud."""
DEFAULT_FACING = 90.0
"""``ReconstructConfig.facing`` by default: a side view with the front to the right (the SRN input view)."""
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
    """Fraction of the frame the object's longer side takes with ``auto``; None = the model's training fill
    (:attr:`Reconstructor.default_fill`)."""
    render_resolution: int | None = None
    """Side of the rendered views; None = the training resolution."""
    mesh_resolution: int = 128
    """Marching-cubes samples along the frustum box's longest side (0 = no mesh)."""
    mesh_threshold: float | str = LOCAL_LEVEL
    """Density level of the mesh surface, or a rule (:mod:`depthnerf.render.mesh_level`): ``"local"`` (the default:
    each input ray's half-maximum, clipped to the photo's mask, which keeps thin parts; docs/RESULTS.md, "Mesh
    level rules"), ``"auto"`` (one level, a tighter surface without them) or ``"silhouette"``."""
    mesh_keep: str = "all"
    """``all`` pieces of the mesh, or the ``largest`` connected piece only (:func:`~depthnerf.render.mesh.keep_pieces`;
    the manifest records the pieces and the faces kept either way)."""
    mesh_colors: str = PHOTO
    """Vertex colour rule (:mod:`depthnerf.render.mesh_colors`): ``photo`` (the photo's colour where it sees the
    vertex or, with a mirror plane, its mirror image; elsewhere ``normal-ray``'s), ``normal-ray`` (the renderer's
    colour along a short ray into the surface) or ``point`` (the field at the vertex)."""
    mesh_fill: float = PHOTO_FILL
    """``photo`` colours: how far the photo's colours spread over the surface into what it does not see, in world
    units per unit of the field's RMS colour error where it sees (0: no spread, the field's colours there)."""
    max_points: int | None = 200_000
    """Largest point-cloud size (None: every point)."""
    chunk: int | None = None
    """Rays per render pass; None: the session's (the device policy's: 4096 on the CPU, 65536 on CUDA)."""
    guided: GuidedConfig | int | bool | None = None
    """Render with depth-guided sampling: a budget, True for the default one, or a :class:`GuidedConfig`
    (:func:`~depthnerf.render.source_guide.as_guided`); False: the checkpoint's own sampler; None: the session's
    guided setup (by default the checkpoint's own sampler)."""
    progress: bool = False
    """Show a progress bar (stderr)."""
    background_removal: str = "auto"
    """``auto`` (a background model when one is installed), ``on`` or ``off``
    (:mod:`depthnerf.reconstruct.background`)."""
    background_model: str | None = None
    """rembg model name or ONNX file; None = :data:`~depthnerf.reconstruct.background.DEFAULT_MODEL`."""
    facing: float | str | None = DEFAULT_FACING
    """Mirror models (``PixelNeRFConfig.mirror``): which way the object's front points, degrees from the direction
    towards the camera, turning towards the image's right (0 = facing the camera, 90 = facing right, 180 = away,
    270 = facing left; 90 and 270 give the same plane). Its mirror plane is the vertical plane through the object
    centre along the front (:func:`~depthnerf.data.symmetry.facing_plane`). Default 90: a side view, as the SRN
    protocol's input view. ``"auto"``: estimated from the photo (:mod:`depthnerf.infer.facing`): read by the
    checkpoint's facing head when it has one (``depthnerf fit-facing``), else the plane that renders the photo best
    (no plane when none renders it better). None = no plane: the model's no-plane mode. Ignored by other models."""
    facing_min_confidence: float = MIN_CONFIDENCE
    """``facing="auto"`` with a facing head: no plane where the head's confidence in its reading is below this
    (:meth:`~depthnerf.model.facing_head.FacingHead.confidence`; 0, the default: the head's plane always)."""

    def __post_init__(self) -> None:
        """One line naming the setting (as its ``depthnerf reconstruct`` flag) when a value cannot work."""
        for name, value, least in (("views", self.views, 1), ("render_resolution", self.render_resolution, 1),
                                   ("chunk", self.chunk, 1), ("max_points", self.max_points, 0)):
            if value is not None and (isinstance(value, bool) or not isinstance(value, int | np.integer)):
                raise DepthnerfError(f"--{name.replace('_', '-')} must be a whole number, got {value!r}")
            if value is not None and least is not None and value < least:
                raise DepthnerfError(f"--{name.replace('_', '-')} must be >= {least}, got {value}")
        check_mesh_resolution(self.mesh_resolution)
        check_mesh_keep(self.mesh_keep)
        check_color_rule(self.mesh_colors)
        parse_level(str(self.mesh_threshold))  # a level <= 0 or NaN made an empty mesh or every cell a surface
        if isinstance(self.mesh_fill, bool) or not isinstance(self.mesh_fill, int | float) or \
                not (math.isfinite(self.mesh_fill) and self.mesh_fill >= 0):
            raise DepthnerfError(f"--mesh-fill must be a number >= 0, got {self.mesh_fill!r}")
        for name, value in (("radius", self.radius), ("focal", self.focal)):
            if value is not None and not (math.isfinite(value) and value > 0):
                raise DepthnerfError(f"--{name} must be > 0, got {value}")
        if not (math.isfinite(self.elevation) and -89.0 <= self.elevation <= 89.0):
            raise DepthnerfError(f"--elevation must be within [-89, 89] degrees, got {self.elevation}")
        if self.fill is not None and not 0 < self.fill <= 1:
            raise DepthnerfError(f"--fill must be in (0, 1], got {self.fill}")
        if self.facing is not None and self.facing != AUTO and (
                isinstance(self.facing, bool) or not isinstance(self.facing, int | float)
                or not math.isfinite(self.facing)):
            raise DepthnerfError(f"--facing must be a finite angle in degrees, 'auto' or 'none', got {self.facing!r}")
        check_min_confidence(self.facing_min_confidence)
        if self.framing not in ("auto", "keep"):
            raise DepthnerfError(f"--framing must be 'auto' or 'keep', got {self.framing!r}")
        if self.background_removal not in MODES:
            raise DepthnerfError(f"--background-removal must be one of {', '.join(MODES)}, "
                                 f"got {self.background_removal!r}")


class Reconstructor:
    """Turns one photo into novel views, depths, a mesh and a point cloud, over an inference session."""

    def __init__(self, session: InferenceSession) -> None:
        """``session``: the checkpoint with its overrides resolved (:meth:`from_pretrained` makes one)."""
        self.session = session
        self._removers: dict[tuple[str, str | None], BackgroundRemover] = {}

    @classmethod
    def from_pretrained(cls, checkpoint: str | Path | Pretrained, device: torch.device | str = "cpu",
                        depth_estimator: str | None = None, depth_checkpoint: str | None = None,
                        **options: Any) -> Reconstructor:
        """Load a shipped name, weights file, checkpoint folder, run folder or Hub file (``hf://OWNER/REPO``;
        ``load_pretrained``) into a session on photos; ``depth_estimator`` / ``depth_checkpoint`` (``--depth`` /
        ``--depth-checkpoint``) override the checkpoint's prior, ``options`` are further
        :class:`~depthnerf.infer.session.SessionOptions` (``fp32``, ``compile``, ``compile_mode``, ``bf16_residual``,
        ``gather``, ``chunk``, ``guided``, ``samples``, ``pixel_center``, ``policy``, ``inputs``)."""
        return cls(InferenceSession(checkpoint, SessionOptions(device=device, depth=depth_estimator,
                                                               depth_checkpoint=depth_checkpoint, **options)))

    @property
    def pretrained(self) -> Pretrained:
        """The loaded checkpoint (its own spec: ``pretrained.spec``; the resolved one: ``session.spec``)."""
        return self.session.pretrained

    @property
    def framing(self) -> str:
        """Framing of the model's training data (``session.framing``)."""
        return self.session.framing

    def background_remover(self, mode: str = "auto", model: str | None = None) -> BackgroundRemover:
        """The background remover of ``mode`` / ``model`` (loaded on first use, then kept; a model that is not
        there is asked for again next time, so a download in between is picked up)."""
        key = (mode, model)
        if key not in self._removers:
            remover = choose_remover(mode, model)
            if not remover.available and mode != "off":
                return remover
            self._removers[key] = remover
        return self._removers[key]

    @property
    def has_facing_head(self) -> bool:
        """Whether the checkpoint carries a facing head, which ``facing="auto"`` then takes
        (:mod:`depthnerf.infer.facing`)."""
        return self.session.pretrained.facing_head is not None

    @property
    def default_fill(self) -> float:
        """The fill the model was trained at (``ReconstructConfig.fill`` when it is None): that of the framing of
        its training data (``InferenceSpec.framing``, :func:`category_fill`)."""
        return category_fill(self.session.spec.category, self.framing)

    @torch.no_grad()
    def reconstruct(self, image: ImageLike, mask: ImageLike | None = None, views: int | None = None,
                    config: ReconstructConfig | None = None, background: BackgroundRemover | None = None
                    ) -> Reconstruction:
        """Reconstruct one photo (see the module docstring); ``views`` (default 36) overrides ``config.views``;
        ``background`` (e.g. over your own rembg session) replaces the config's background removal."""
        cfg = config or ReconstructConfig()
        if views is not None:
            cfg = replace(cfg, views=views)
        views = cfg.views
        spec = self.session.spec
        times: dict[str, float] = {}
        t = time.perf_counter()
        res = spec.resolution
        if cfg.radius is not None and cfg.focal is not None:
            radius, focal, image_size = cfg.radius, cfg.focal, SRN_IMAGE_SIZE  # --focal's frame: SRN's
        else:
            if spec.category not in CATEGORY_DEFAULTS:
                raise DepthnerfError(
                    f"{self.session.name}: unknown SRN category {spec.category!r} in the checkpoint's spec (known: "
                    f"{', '.join(sorted(CATEGORY_DEFAULTS))}), so no default camera; pass both --radius and --focal "
                    "(focal in pixels of a 128 px frame)")
            cat = category_defaults(spec.category)
            radius = cfg.radius if cfg.radius is not None else cat.camera_radius
            focal = cfg.focal if cfg.focal is not None else cat.focal
            image_size = cat.image_size
        fill = cfg.fill if cfg.fill is not None else self.default_fill
        if background is None:
            background = self.background_remover(cfg.background_removal, cfg.background_model)
        prepared = prepare_photo(image, mask, res, cfg.framing, fill, background)
        times["prepare_s"] = time.perf_counter() - t
        poses = orbit_poses(radius, cfg.elevation, views)
        pixel_center = spec.pixel_center  # the photo's SRN-style intrinsics read as training read the data
        intr = srn_intrinsics(focal, image_size, res, pixel_center)
        render_intr = srn_intrinsics(focal, image_size, cfg.render_resolution or res, pixel_center)
        img_t = torch.from_numpy(prepared.image).permute(2, 0, 1)[None].contiguous()
        mask_t = torch.from_numpy(prepared.mask)[None]
        t = time.perf_counter()
        fit = None
        if cfg.facing == AUTO and self.session.model.cfg.mirror:
            encoded = self.session.encode(img_t, mask_t, poses[0], intr)
            times["encode_s"] = time.perf_counter() - t
            t = time.perf_counter()
            fit = fit_facing(self.session, encoded, min_confidence=cfg.facing_min_confidence)
            times["facing_s"] = time.perf_counter() - t
            plane, symmetry = self.symmetry(fit.facing, fit, cfg.facing_min_confidence)
            encoded = replace(encoded, enc=with_plane(encoded.enc, plane))
        else:
            plane, symmetry = self.symmetry(None if cfg.facing == AUTO else cfg.facing)
            encoded = self.session.encode(img_t, mask_t, poses[0], intr, symmetry_plane=plane)
            times["encode_s"] = time.perf_counter() - t
        result = self.reconstruct_encoded(encoded, poses, render_intr, cfg, prepared)
        result.timings = {**times, **result.timings}
        result.settings = {"radius": radius, "elevation": cfg.elevation, "focal": focal, "focal_frame": image_size,
                           "framing": cfg.framing, "fill": fill,
                           "facing": cfg.facing if fit is None else fit.facing,
                           "facing_fit": None if fit is None else fit.as_dict(),
                           "symmetry_plane": None if plane is None else list(plane), "symmetry": symmetry,
                           "training_framing": self.framing,
                           "background_removal": cfg.background_removal,
                           "background_model": None if prepared.cutout is None else background.name,
                           "background_model_licence": None if prepared.cutout is None else background.licence,
                           **result.settings}
        return result

    def symmetry(self, facing: float | None, fit: FacingFit | None = None, min_confidence: float = MIN_CONFIDENCE
                 ) -> tuple[tuple[float, float, float, float] | None, str]:
        """The mirror plane for an object facing ``facing`` degrees (``ReconstructConfig.facing``; ``fit``: the
        estimate it came from, with ``min_confidence`` its head's threshold) and a line saying which plane is
        used, or why none."""
        if not self.session.model.cfg.mirror:
            return None, "off: the model has no mirror-symmetric conditioning"
        if fit is not None:
            errors = f"input-view error {fit.error:.5f} with it, {fit.none_error:.5f} without a plane"
            if facing is None and fit.confidence is not None:
                return None, (f"off: the checkpoint's facing head is unsure of the facing (confidence "
                              f"{fit.confidence:.2f} < --facing-min-confidence {min_confidence:g}; it read "
                              f"{fit.best:g} degrees, {errors})")
            if facing is None:
                return None, (f"off: --facing auto found no plane that renders the photo better than none (best: "
                              f"{fit.best:g} degrees, {errors})")
            how = (f"the checkpoint's facing head, confidence {fit.confidence:.2f}; " if fit.confidence is not None
                   else "")
            return facing_plane(facing), f"on: the object faces {facing:g} degrees (--facing auto: {how}{errors})"
        if facing is None:
            return None, "off: no facing given (the model's no-plane mode)"
        default = " (the default: a side view)" if facing == DEFAULT_FACING else ""
        return facing_plane(facing), f"on: the object faces {facing:g} degrees{default}"

    def encode_view(self, image: Float[torch.Tensor, "1 3 H W"], mask: Bool[torch.Tensor, "1 H W"],
                    pose: Float[torch.Tensor, "4 4"], intr: Intrinsics, *,
                    depth: Float[torch.Tensor, "1 H W"] | None = None,
                    symmetry_plane: tuple[float, ...] | None = None) -> EncodedView:
        """Condition one view on its prior and encode it (:meth:`InferenceSession.encode
        <depthnerf.infer.session.InferenceSession.encode>`; ``symmetry_plane``: the object's mirror plane for
        mirror models, :meth:`symmetry`)."""
        return self.session.encode(image, mask, pose, intr, depth=depth, symmetry_plane=symmetry_plane)

    def _guided(self, cfg: ReconstructConfig) -> GuidedConfig | None:
        """The guided setup of one call: ``cfg.guided`` (:func:`~depthnerf.render.source_guide.as_guided`), or the
        session's when it is None."""
        return self.session.guided if cfg.guided is None else as_guided(cfg.guided, "ReconstructConfig.guided")

    def render(self, encoded: EncodedView, poses: Float[torch.Tensor, "N 4 4"], intr: Intrinsics,
               cfg: ReconstructConfig, on_group: Callable[[int], Any] | None = None) -> ViewRenders:
        """Render ``poses`` of an encoded view at ``intr`` (depth-guided with ``cfg.guided`` or the session's)."""
        guided = self._guided(cfg)
        return self.session.render(encoded, poses, intr, guided=guided, chunk=cfg.chunk, on_group=on_group)

    @torch.no_grad()
    def reconstruct_encoded(self, encoded: EncodedView, poses: Float[torch.Tensor, "N 4 4"],
                            render_intr: Intrinsics, cfg: ReconstructConfig, prepared: PreparedImage | None = None,
                            on_stage: Callable[[int], Any] | None = None) -> Reconstruction:
        """The orbit ``poses`` rendered at ``render_intr``, the mesh of the input frustum and the point cloud."""
        spec = self.session.spec
        near, far = spec.z_range
        guided = self._guided(cfg)
        times: dict[str, float] = {}
        bar = tqdm(total=len(poses) + 1, desc="reconstruct", unit="step", file=sys.stderr, disable=not cfg.progress)
        t = time.perf_counter()
        out = self.render(encoded, poses, render_intr, cfg, bar.update)
        times["render_s"] = time.perf_counter() - t
        if on_stage is not None:
            on_stage(1)
        t = time.perf_counter()
        mesh, level = trimesh.Trimesh(), None
        mesh_cfg = MeshConfig(cfg.mesh_resolution, cfg.mesh_threshold, colors=cfg.mesh_colors,
                              photo_fill=cfg.mesh_fill)
        if cfg.mesh_resolution > 0:
            mesh, level = self.session.mesh(encoded, mesh_cfg)
        mesh, pieces = keep_pieces(mesh, cfg.mesh_keep)
        bar.update(1)
        bar.close()
        times["mesh_s"] = time.perf_counter() - t
        if on_stage is not None:
            on_stage(1)
        points, colors = orbit_points(out, poses, render_intr, POINT_OPACITY, cfg.max_points)
        if prepared is None:
            prepared = PreparedImage(image=encoded.inputs.images[0, 0].permute(1, 2, 0).cpu().numpy(),
                                     mask=encoded.mask[0].numpy(), notes=[],
                                     source_size=(encoded.intr.height, encoded.intr.width))
        disparity, normalized = encoded.disparity, encoded.inputs.disparity
        settings = {"resolution": spec.resolution, "render_resolution": render_intr.height, "views": len(poses),
                    "z_range": [near, far], "category": spec.category, "pixel_center": spec.pixel_center,
                    "encoder_norm": self.session.options.encoder_norm,
                    "depth_estimator": spec.prior.estimator, "depth_checkpoint": spec.prior.checkpoint,
                    "guided_sampling": None if guided is None else guided.budget,
                    "sampler_counts": list(spec.render.sampler.counts),
                    "mesh_resolution": cfg.mesh_resolution, "mesh_threshold": cfg.mesh_threshold,
                    "mesh_level": level and level.level, "mesh_level_rule": level and level.describe(),
                    "mesh_keep": cfg.mesh_keep, "mesh_pieces": pieces.pieces, "mesh_faces_extracted": pieces.faces,
                    "mesh_faces_kept": pieces.kept_faces,
                    "point_opacity": POINT_OPACITY,
                    "mesh_color_rule": mesh_cfg.colors,
                    "mesh_colors": describe_colors(mesh_cfg.colors, mesh_cfg.color_half_width, mesh_cfg.photo_fill)}
        return Reconstruction(
            input=prepared, depth_prior=None if disparity is None else disparity[0].numpy(),
            prior_normalized=None if normalized is None else normalized[0, 0, 0].cpu().numpy(),
            poses=poses.numpy(), intrinsics=render_intr, views=out.rgb.numpy(), depths=out.distance.numpy(),
            opacity=out.opacity.numpy(), mesh=mesh, points=points.astype(np.float32),
            point_colors=colors.astype(np.float32), settings=settings, timings=times)

    def save(self, result: Reconstruction, out_dir: str | Path) -> dict[str, Any]:
        """Write every output into ``out_dir`` and return the manifest (also ``out_dir/manifest.json``); an earlier
        reconstruction's files there are replaced, other files left (:mod:`depthnerf.reconstruct.exports`)."""
        return save_reconstruction(result, Path(out_dir), self.session.provenance())
