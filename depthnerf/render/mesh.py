"""Mesh extraction from a density field by marching cubes over a grid in the source camera's frame.

Grid
    A :class:`CameraGrid` is an axis-aligned box in the camera frame of a pose ``c2w`` (OpenCV axes, see
    ``depthnerf.data.cameras``). :meth:`CameraGrid.from_frustum` spans camera z in ``[z_near, z_far]`` and, laterally,
    everything the image sees up to ``z_far`` (image edges at pixel borders ``-0.5`` and ``W - 0.5``). pixelNeRF's
    near/far are ray distances; used as z bounds they cut only a sliver at the image corners in front of ``z_near``
    (``z = t cos(theta) <= t``), far from a centred object. Voxels are cubes: ``MeshConfig.resolution`` samples along
    the box's longest side, as many as needed (same step) along the others, the grid centred on the box.
    Samples are mapped to world coordinates (``x_world = R x_cam + t``) and the density is queried there, in chunks
    of ``MeshConfig.chunk`` points, so memory stays bounded at any resolution.

Surface
    scikit-image ``marching_cubes`` at a density level (units 1/world-distance; see "Surface level"). With
    ``close_boundary`` the volume is padded by one sample of empty space, so a surface cut by the box is capped and
    the mesh is closed. Faces are oriented outward (density is higher inside, hence ``gradient_direction='ascent'``;
    a closed mesh has positive volume). The mesh is returned in **world** coordinates. A density that never crosses
    the level inside the grid gives an empty mesh (no vertices), never an error; non-finite densities raise
    :class:`~depthnerf.errors.DepthnerfError`.

Surface level
    ``MeshConfig.threshold`` is a fixed density, or :data:`AUTO_LEVEL` (``"auto"``, the default of eval,
    reconstruct and demo), which :func:`auto_level` resolves per object: **level = 0.5 x the median, over the input
    camera's rays whose opacity exceeds 0.5, of the peak density along the ray** (:data:`AUTO_SAMPLES` uniform
    samples between the run's z-near and z-far, from the same density function the mesh samples; opacity
    ``1 - exp(-sum(sigma) * delta)``, what the volume renderer's quadrature gives for those samples). Rationale: a
    ray that renders opaque crosses the object, so its peak density is the object's interior density there, and
    the median over those rays is the typical interior density; half of it is the half-maximum level, the classic
    edge definition (it puts the surface of a blurred step at the step). The rule is scale-free: sharp paper-scale
    models (interior densities in the hundreds) get a high level, soft CPU-preset models (peaks ~5) a low one,
    where a fixed level gives empty meshes. The median ignores a few outlier rays (floaters, glancing rays).
    When no ray is opaque the level falls back to :data:`DEFAULT_THRESHOLD` and :class:`MeshLevel` says so.
    :data:`DEFAULT_THRESHOLD` (20, NeRF practice being 10-50 for unit-scale scenes): a slab 0.05 thick (5% of a
    unit-diagonal SRN object, about a chair leg) at density 20 has opacity ``1 - exp(-20 * 0.05) = 63%``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
import trimesh
from jaxtyping import Float
from skimage.measure import marching_cubes
from torch import Tensor

from depthnerf.data.cameras import Intrinsics, camera_rays
from depthnerf.errors import DepthnerfError
from depthnerf.model.pixelnerf import EncodedViews, FieldRuntime, PixelNeRF

DEFAULT_THRESHOLD = 20.0
"""Fallback density level when no input ray is opaque (see the module docstring)."""
AUTO_LEVEL = "auto"
"""``MeshConfig.threshold`` value asking for the per-object level of :func:`auto_level`."""
AUTO_SAMPLES = 96
"""Uniform samples per input ray for :func:`auto_level`."""
OPAQUE = 0.5
"""Rays whose opacity exceeds this count as opaque in :func:`auto_level`."""

DensityFn = Callable[[Float[Tensor, "N 3"]], Float[Tensor, " N"]]
"""World points -> volume density (a tensor of N values, or N x 1)."""
ColorFn = Callable[[Float[Tensor, "N 3"]], Float[Tensor, "N 3"]]
"""World points -> RGB in [0, 1]."""


@dataclass(frozen=True)
class MeshConfig:
    """Marching-cubes extraction settings."""

    resolution: int = 128
    """Samples along the longest side of the grid box (voxels are cubes)."""
    threshold: float | str = DEFAULT_THRESHOLD
    """Density level of the surface (units 1/world-distance), or :data:`AUTO_LEVEL` (see the module docstring;
    :func:`extract_mesh` needs a number, :func:`source_mesh` resolves ``"auto"``; eval, reconstruct and demo
    default to ``"auto"``)."""
    chunk: int = 65536
    """Points per density query (bounds memory)."""
    close_boundary: bool = True
    """Pad with one sample of empty space so surfaces cut by the box are capped."""


@dataclass(frozen=True)
class CameraGrid:
    """An axis-aligned box in the camera frame of ``c2w``: where the density is sampled."""

    c2w: Float[Tensor, "4 4"]
    """Camera-to-world pose of the (source) camera, OpenCV axes."""
    lo: tuple[float, float, float]
    """Camera-frame box minimum (x, y, z)."""
    hi: tuple[float, float, float]
    """Camera-frame box maximum (x, y, z)."""

    def __post_init__(self) -> None:
        if not all(h > lo_ for lo_, h in zip(self.lo, self.hi, strict=True)):
            raise DepthnerfError(f"mesh grid: empty box lo={self.lo} hi={self.hi}")

    @classmethod
    def from_frustum(cls, c2w: Float[Tensor, "4 4"], intr: Intrinsics, z_near: float, z_far: float) -> CameraGrid:
        """The camera-frame box around the view frustum between camera z ``z_near`` and ``z_far``."""
        if not 0 < z_near < z_far:
            raise DepthnerfError(f"mesh grid: need 0 < z_near < z_far, got {z_near}, {z_far}")
        xs = [(e - intr.cx) / intr.focal * z for e in (-0.5, intr.width - 0.5) for z in (z_near, z_far)]
        ys = [(e - intr.cy) / intr.focal * z for e in (-0.5, intr.height - 0.5) for z in (z_near, z_far)]
        return cls(torch.as_tensor(c2w, dtype=torch.float32), (min(xs), min(ys), z_near), (max(xs), max(ys), z_far))

    @classmethod
    def world_box(cls, lo: tuple[float, float, float], hi: tuple[float, float, float]) -> CameraGrid:
        """A box given directly in world coordinates (identity pose)."""
        return cls(torch.eye(4), tuple(map(float, lo)), tuple(map(float, hi)))

    def layout(self, resolution: int) -> tuple[tuple[int, int, int], float, np.ndarray]:
        """``(shape, step, origin)``: samples per axis, the cube voxel side and the camera-frame first sample."""
        if resolution < 2:
            raise DepthnerfError(f"mesh grid: resolution must be >= 2, got {resolution}")
        lo, hi = np.array(self.lo, dtype=np.float64), np.array(self.hi, dtype=np.float64)
        step = float((hi - lo).max()) / (resolution - 1)
        shape = tuple(int(math.ceil((h - low) / step - 1e-9)) + 1 for low, h in zip(lo, hi, strict=True))
        origin = (lo + hi) / 2 - (np.array(shape) - 1) * step / 2
        return shape, step, origin


@dataclass
class _Volume:
    """Densities on the grid, and where the grid is."""

    values: np.ndarray = field(repr=False)
    """float32 densities, shape ``(nx, ny, nz)``."""
    step: float
    """Voxel side (world distance)."""
    origin: np.ndarray
    """Camera-frame position of sample ``[0, 0, 0]``."""


def _query_chunks(fn: Callable[[Tensor], Tensor], points_of: Callable[[int, int], Tensor], total: int,
                  chunk: int, width: int, what: str) -> np.ndarray:
    """Evaluate ``fn`` on ``points_of(start, stop)`` chunk by chunk; returns ``(total, width)`` float32."""
    out = np.empty((total, width), dtype=np.float32)
    with torch.no_grad():
        for start in range(0, total, chunk):
            stop = min(start + chunk, total)
            values = torch.as_tensor(fn(points_of(start, stop))).detach().float().cpu()
            if values.numel() != (stop - start) * width:
                raise DepthnerfError(f"mesh extraction: {what} returned shape {tuple(values.shape)} for "
                                     f"{stop - start} points (expected {stop - start} x {width})")
            out[start:stop] = values.reshape(stop - start, width).numpy()
    if not np.isfinite(out).all():
        raise DepthnerfError(f"mesh extraction: {what} returned {int((~np.isfinite(out)).sum())} non-finite values")
    return out


def sample_density(density_fn: DensityFn, grid: CameraGrid, config: MeshConfig = MeshConfig(),
                   device: torch.device | str = "cpu") -> _Volume:
    """Evaluate ``density_fn`` at every grid sample (world coordinates), ``config.chunk`` points at a time."""
    shape, step, origin = grid.layout(config.resolution)
    c2w = grid.c2w.to(device=device, dtype=torch.float32)
    origin_t = torch.as_tensor(origin, dtype=torch.float32, device=device)
    dims = torch.tensor([shape[1] * shape[2], shape[2], 1], device=device)
    sizes = torch.tensor(shape, device=device)

    def points_of(start: int, stop: int) -> Tensor:
        flat = torch.arange(start, stop, device=device)
        ijk = (flat[:, None] // dims) % sizes  # row-major (x slowest), matches values.reshape(shape)
        cam = origin_t + ijk.float() * step
        return cam @ c2w[:3, :3].T + c2w[:3, 3]

    total = shape[0] * shape[1] * shape[2]
    values = _query_chunks(density_fn, points_of, total, config.chunk, 1, "density_fn")
    return _Volume(values.reshape(shape), step, origin)


def extract_mesh(density_fn: DensityFn, grid: CameraGrid, config: MeshConfig = MeshConfig(),
                 color_fn: ColorFn | None = None, device: torch.device | str = "cpu") -> trimesh.Trimesh:
    """Marching-cubes surface of ``density_fn`` at ``config.threshold`` over ``grid``, in world coordinates.

    ``color_fn`` (optional) colours the vertices (RGB in [0, 1] at the world vertex positions). Returns an empty
    mesh when the density never crosses the threshold inside the grid.
    """
    if not isinstance(config.threshold, int | float):
        raise DepthnerfError(f"mesh extraction: needs a numeric level, got {config.threshold!r} (see source_mesh)")
    vol = sample_density(density_fn, grid, config, device)
    values, origin = vol.values, vol.origin
    if config.close_boundary:
        values = np.pad(values, 1, mode="constant", constant_values=min(0.0, config.threshold - 1.0))
        origin = origin - vol.step
    if not values.min() < config.threshold < values.max():  # no crossing: nothing to extract
        return trimesh.Trimesh()
    verts, faces, _, _ = marching_cubes(values, level=config.threshold, spacing=(vol.step,) * 3,
                                   gradient_direction="ascent")  # density rises inward: outward faces
    rot = grid.c2w[:3, :3].double().numpy()
    trans = grid.c2w[:3, 3].double().numpy()
    verts_world = (verts.astype(np.float64) + origin) @ rot.T + trans
    mesh = trimesh.Trimesh(vertices=verts_world, faces=faces, process=False)
    if color_fn is not None and len(verts_world):
        pts = torch.as_tensor(verts_world, dtype=torch.float32, device=device)
        rgb = _query_chunks(color_fn, lambda a, b: pts[a:b], len(pts), config.chunk, 3, "color_fn")
        rgba = np.concatenate([np.round(np.clip(rgb, 0, 1) * 255), np.full((len(rgb), 1), 255)], axis=1)
        mesh.visual.vertex_colors = rgba.astype(np.uint8)
    return mesh


@dataclass(frozen=True)
class MeshLevel:
    """The density level a mesh was extracted at, and how it was chosen."""

    level: float
    """Marching-cubes density level."""
    rule: str
    """``fixed`` (given), ``auto`` (:func:`auto_level`) or ``fallback`` (auto, no opaque ray: the default)."""
    opaque_rays: int = 0
    """Input rays with opacity > :data:`OPAQUE` (auto rules only)."""
    rays: int = 0
    """Input rays examined (auto rules only)."""

    def describe(self) -> str:
        """One line for records (summary, manifest)."""
        if self.rule == "fixed":
            return f"fixed density level {self.level:g}"
        if self.rule == "fallback":
            return (f"auto level: no opaque input ray (0 of {self.rays}), fell back to density {self.level:g}")
        return (f"auto level {self.level:.4g} = 0.5 x median peak density over {self.opaque_rays} of {self.rays} "
                f"opaque input rays")


def parse_level(text: str) -> float | str:
    """``--mesh-threshold`` value: a positive number or ``auto``."""
    if text.strip().lower() == AUTO_LEVEL:
        return AUTO_LEVEL
    try:
        value = float(text)
    except ValueError:
        raise DepthnerfError(f"--mesh-threshold: expected a number or 'auto', got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise DepthnerfError(f"--mesh-threshold: must be a positive number or 'auto', got {text!r}")
    return value


def auto_level(density_fn: DensityFn, c2w: Float[Tensor, "4 4"], intr: Intrinsics, near: float, far: float,
               samples: int = AUTO_SAMPLES, chunk: int = 65536, device: torch.device | str = "cpu",
               ray_stride: int = 2) -> MeshLevel:
    """Half the median peak density over the opaque rays of the camera ``(c2w, intr)`` (module docstring); the
    rays of every ``ray_stride``-th pixel row and column (a median needs no more, and it is 4x cheaper)."""
    if not 0 < near < far or samples < 1:
        raise DepthnerfError(f"auto mesh level: need 0 < near < far and samples >= 1, got {near}, {far}, {samples}")
    origins, dirs = camera_rays(torch.as_tensor(c2w, dtype=torch.float32), intr)
    origins, dirs = origins[::ray_stride, ::ray_stride], dirs[::ray_stride, ::ray_stride]
    origins, dirs = origins.reshape(-1, 3).to(device), dirs.reshape(-1, 3).to(device)
    delta = (far - near) / samples
    t = near + (torch.arange(samples, device=device, dtype=torch.float32) + 0.5) * delta  # bin midpoints

    def points_of(start: int, stop: int) -> Tensor:
        flat = torch.arange(start, stop, device=device)
        ray, k = flat // samples, flat % samples
        return origins[ray] + t[k, None] * dirs[ray]

    rays = len(dirs)
    sigma = _query_chunks(density_fn, points_of, rays * samples, chunk, 1, "density_fn").reshape(rays, samples)
    opacity = 1.0 - np.exp(-np.clip(sigma, 0, None).astype(np.float64).sum(1) * delta)
    opaque = opacity > OPAQUE
    if not opaque.any():
        return MeshLevel(DEFAULT_THRESHOLD, "fallback", 0, rays)
    return MeshLevel(0.5 * float(np.median(sigma.max(1)[opaque])), "auto", int(opaque.sum()), rays)


def source_mesh(density_fn: DensityFn, c2w: Float[Tensor, "4 4"], intr: Intrinsics, near: float, far: float,
                config: MeshConfig = MeshConfig(), color_fn: ColorFn | None = None,
                device: torch.device | str = "cpu") -> tuple[trimesh.Trimesh, MeshLevel]:
    """The mesh over the frustum box of the (input) camera ``(c2w, intr)`` between ``near`` and ``far``, at
    ``config.threshold`` (a number, or ``"auto"`` resolved by :func:`auto_level` along that camera's rays)."""
    if config.threshold == AUTO_LEVEL:
        level = auto_level(density_fn, c2w, intr, near, far, chunk=config.chunk, device=device)
    elif isinstance(config.threshold, int | float):
        level = MeshLevel(float(config.threshold), "fixed")
    else:
        raise DepthnerfError(f"mesh level must be a number or 'auto', got {config.threshold!r}")
    grid = CameraGrid.from_frustum(c2w, intr, near, far)
    mesh = extract_mesh(density_fn, grid, replace(config, threshold=level.level), color_fn, device)
    return mesh, level


def levels_text(levels: list[MeshLevel], resolution: int) -> str:
    """How several meshes were extracted, for ``summary.json`` ``mesh_status``."""
    grid = f"on a {resolution}-sample frustum grid"
    if not levels:
        return "no mesh"
    if all(lv.rule == "fixed" for lv in levels):
        return f"marching cubes at fixed density level {levels[0].level:g} {grid}"
    values = [lv.level for lv in levels]
    fallback = sum(lv.rule == "fallback" for lv in levels)
    return (f"marching cubes {grid} at the auto level per object (0.5 x median peak density over opaque input rays; "
            f"per_object.csv mesh_level): median {float(np.median(values)):.4g}, range {min(values):.4g}-"
            f"{max(values):.4g}"
            + (f"; {fallback} object(s) without an opaque ray fell back to {DEFAULT_THRESHOLD:g}" if fallback else ""))


MESH_KEEP = ("all", "largest")
"""What an export keeps of an extracted mesh: every piece, or the largest connected piece (:func:`keep_pieces`)."""


@dataclass(frozen=True)
class MeshPieces:
    """How an extracted mesh falls apart into connected pieces, and what :func:`keep_pieces` kept."""

    pieces: int
    """Connected pieces (faces joined by a shared edge) of the extracted mesh."""
    faces: int
    """Faces of the extracted mesh."""
    kept_faces: int
    """Faces of the returned mesh."""


def check_mesh_keep(keep: str) -> None:
    """One line naming ``--mesh-keep`` when ``keep`` is not one of :data:`MESH_KEEP`."""
    if keep not in MESH_KEEP:
        raise DepthnerfError(f"--mesh-keep must be one of {', '.join(MESH_KEEP)}, got {keep!r}")


def keep_pieces(mesh: trimesh.Trimesh, keep: str) -> tuple[trimesh.Trimesh, MeshPieces]:
    """``mesh`` whole (``keep="all"``) or only its largest connected piece (``"largest"``: the piece with the most
    faces, faces being connected when they share an edge; the first such piece on a tie), with unused vertices
    dropped, and the :class:`MeshPieces` count. An export filter on top of a clean field, never a substitute for
    one: the field itself is unchanged."""
    check_mesh_keep(keep)
    faces = len(mesh.faces)
    if faces == 0:
        return mesh, MeshPieces(0, 0, 0)
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=faces)
    counts = np.bincount(labels)
    if keep == "all" or len(counts) == 1:
        return mesh, MeshPieces(len(counts), faces, faces)
    main = labels == int(np.argmax(counts))
    kept = mesh.submesh([np.flatnonzero(main)], append=True, repair=False)
    return kept, MeshPieces(len(counts), faces, int(main.sum()))


def load_mesh(path: Path) -> trimesh.Trimesh:
    """Read a mesh file (``mesh.ply`` of an SRN-format object) as one triangle mesh with at least one face."""
    path = Path(path)
    if not path.is_file():
        raise DepthnerfError(f"{path}: mesh file not found")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as err:  # trimesh raises many types for malformed files
        raise DepthnerfError(f"{path}: cannot read mesh ({type(err).__name__}: {err})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise DepthnerfError(f"{path}: mesh has no triangles")
    if not np.isfinite(mesh.vertices).all():
        raise DepthnerfError(f"{path}: mesh has non-finite vertices")
    return mesh


def field_queries(model: PixelNeRF, enc: EncodedViews, eye: Float[Tensor, " 3"],
                  runtime: FieldRuntime | None = None
                  ) -> tuple[Callable[[Tensor], Tensor], Callable[[Tensor], Tensor]]:
    """``(density_fn, color_fn)`` of the fine network (the coarse one without a fine network) at world points
    ``[N, 3]``, each point viewed along the ray from ``eye`` (the input camera centre) through it, run as
    ``runtime`` says (None: the default)."""
    fn = model.field(enc, "fine", runtime)

    def query(points: Tensor) -> tuple[Tensor, Tensor]:
        dirs = torch.nn.functional.normalize(points - eye.to(points), dim=-1)
        rgb, sigma = fn(points[None, :, None, :], dirs[None])
        return rgb[0, :, 0], sigma[0, :, 0]

    return (lambda p: query(p)[1]), (lambda p: query(p)[0])


def input_camera_mesh(model: PixelNeRF, enc: EncodedViews, c2w: Float[Tensor, "4 4"], intr: Intrinsics, near: float,
                      far: float, config: MeshConfig, device: torch.device | str, colored: bool = True,
                      runtime: FieldRuntime | None = None) -> tuple[trimesh.Trimesh, MeshLevel]:
    """The mesh over the input camera's frustum box (fine network density, each point seen along the input
    camera's ray through it), with the network's colour at each vertex when ``colored``; the field runs as
    ``runtime`` says (None: the default)."""
    density_fn, color_fn = field_queries(model, enc, c2w[:3, 3].to(device), runtime)
    return source_mesh(density_fn, c2w, intr, near, far, config, color_fn if colored else None, device)
