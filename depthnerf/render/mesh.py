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
    ``MeshConfig.threshold`` is a fixed density or a per-object rule (``"auto"``, the default of eval;
    ``"silhouette"``; ``"local"``, the default of reconstruct and the demo), resolved from the densities along the
    input camera's rays: see :mod:`depthnerf.render.mesh_level`.

Colours
    :func:`input_camera_mesh` colours the vertices by ``MeshConfig.colors`` (:mod:`depthnerf.render.mesh_colors`):
    by default (``photo``) the input photo's colour where it sees the vertex or its mirror image, elsewhere the
    renderer's colour of a short ray that looks at the vertex from outside along its normal (``normal-ray``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
import torch
import trimesh
from jaxtyping import Bool, Float
from skimage.measure import marching_cubes
from torch import Tensor

from depthnerf.data.cameras import Intrinsics
from depthnerf.errors import DepthnerfError
from depthnerf.model.pixelnerf import EncodedViews, FieldRuntime, PixelNeRF
from depthnerf.render.mesh_colors import RadianceFn, seen_from, vertex_colors
from depthnerf.render.mesh_level import DEFAULT_THRESHOLD, DensityFn, MeshLevel, level_surface, query_chunks
from depthnerf.render.photo_colors import PHOTO, PHOTO_FILL, PhotoView

ColorFn = Callable[[Float[Tensor, "N 3"]], Float[Tensor, "N 3"]]
"""World points -> RGB in [0, 1]."""


@dataclass(frozen=True)
class MeshConfig:
    """Marching-cubes extraction settings."""

    resolution: int = 128
    """Samples along the longest side of the grid box (voxels are cubes)."""
    threshold: float | str = DEFAULT_THRESHOLD
    """Density level of the surface (units 1/world-distance), or a rule name of
    :mod:`depthnerf.render.mesh_level` (``"auto"``, ``"silhouette"``, ``"local"``): :func:`extract_mesh` needs a number,
    :func:`source_mesh` resolves a rule; eval defaults to ``"auto"``, reconstruct and the demo to
    ``"local"``."""
    chunk: int = 65536
    """Points per density query (bounds memory)."""
    close_boundary: bool = True
    """Pad with one sample of empty space so surfaces cut by the box are capped."""
    colors: str = PHOTO
    """Vertex colour rule of :func:`input_camera_mesh` (:mod:`depthnerf.render.mesh_colors`): ``"photo"`` (the
    default: the input photo's colour where it sees the vertex or its mirror image, else ``normal-ray``'s),
    ``"normal-ray"`` (the renderer's colour along a short ray into the surface) or ``"point"`` (the field at the
    vertex). docs/RESULTS.md, "Mesh vertex colours" measures them."""
    color_half_width: float = 0.06
    """``normal-ray`` (and ``photo`` where the photo does not see): the short ray's half-width (world units; the
    study measured 0.015-0.1 on cars and chairs)."""
    color_samples: int = 24
    """``normal-ray``: samples along the short ray."""
    photo_fill: float = PHOTO_FILL
    """``photo``: how far the photo's colours spread into what it does not see, in world units per unit of the
    field's RMS colour error where it sees (:func:`~depthnerf.render.photo_colors.photo_blend`; 0: no spread)."""


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
    values = query_chunks(density_fn, points_of, total, config.chunk, 1, "density_fn")
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
        rgb = query_chunks(color_fn, lambda a, b: pts[a:b], len(pts), config.chunk, 3, "color_fn")
        rgba = np.concatenate([np.round(np.clip(rgb, 0, 1) * 255), np.full((len(rgb), 1), 255)], axis=1)
        mesh.visual.vertex_colors = rgba.astype(np.uint8)
    return mesh


def source_mesh(density_fn: DensityFn, c2w: Float[Tensor, "4 4"], intr: Intrinsics, near: float, far: float,
                config: MeshConfig = MeshConfig(), color_fn: ColorFn | None = None,
                device: torch.device | str = "cpu", mask: Bool[np.ndarray, "H W"] | None = None
                ) -> tuple[trimesh.Trimesh, MeshLevel]:
    """The mesh over the frustum box of the (input) camera ``(c2w, intr)`` between ``near`` and ``far``, at
    ``config.threshold`` (a number, or a rule of :mod:`depthnerf.render.mesh_level` resolved along that camera's
    rays; ``mask``, the camera's object mask, is the ``silhouette`` rule's target)."""
    level, surface_fn, value = level_surface(config.threshold, density_fn, c2w, intr, near, far, config.chunk,
                                             device, mask)
    grid = CameraGrid.from_frustum(c2w, intr, near, far)
    mesh = extract_mesh(surface_fn, grid, replace(config, threshold=value), color_fn, device)
    return mesh, level


MAX_RESOLUTION = 1024
"""The finest mesh grid a command accepts: 1024 samples along the longest side are up to 1024^3 density queries
(about 10^9), and their float32 densities alone take 4.3 GB before marching cubes copies them."""


def check_mesh_resolution(resolution: int, flag: str = "--mesh-resolution", none_allowed: bool = True) -> None:
    """One line naming ``flag`` when ``resolution`` is not a whole number in ``[2, MAX_RESOLUTION]`` (or 0, "no
    mesh", where ``none_allowed``): said before any work starts, not when the grid's memory runs out."""
    if isinstance(resolution, bool) or not isinstance(resolution, int | np.integer):
        raise DepthnerfError(f"{flag} must be a whole number, got {resolution!r}")
    if none_allowed and resolution == 0:
        return
    if not 2 <= resolution <= MAX_RESOLUTION:
        lowest = "0 (no mesh) or >= 2" if none_allowed else ">= 2"
        raise DepthnerfError(f"{flag} must be {lowest} and at most {MAX_RESOLUTION} (up to {MAX_RESOLUTION}^3 "
                             f"density samples, 4.3 GB), got {resolution}")


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


def field_radiance(model: PixelNeRF, enc: EncodedViews, runtime: FieldRuntime | None = None) -> RadianceFn:
    """The fine network (the coarse one without a fine network) as a :data:`~depthnerf.render.mesh_colors.RadianceFn`:
    points ``[N, S, 3]`` seen along directions ``[N, 3]`` -> ``(rgb [N, S, 3], density [N, S])``."""
    fn = model.field(enc, "fine", runtime)

    def radiance(points: Tensor, dirs: Tensor) -> tuple[Tensor, Tensor]:
        rgb, sigma = fn(points[None], dirs[None])
        return rgb[0], sigma[0]

    return radiance


def field_queries(model: PixelNeRF, enc: EncodedViews, eye: Float[Tensor, " 3"],
                  runtime: FieldRuntime | None = None
                  ) -> tuple[Callable[[Tensor], Tensor], Callable[[Tensor], Tensor]]:
    """``(density_fn, color_fn)`` of the fine network (the coarse one without a fine network) at world points
    ``[N, 3]``, each point viewed along the ray from ``eye`` (the input camera centre) through it, run as
    ``runtime`` says (None: the default)."""
    radiance = field_radiance(model, enc, runtime)
    return (lambda p: seen_from(radiance, p, eye)[1]), (lambda p: seen_from(radiance, p, eye)[0])


def input_camera_mesh(model: PixelNeRF, enc: EncodedViews, c2w: Float[Tensor, "4 4"], intr: Intrinsics, near: float,
                      far: float, config: MeshConfig, device: torch.device | str, colored: bool = True,
                      runtime: FieldRuntime | None = None, mask: Bool[np.ndarray, "H W"] | None = None,
                      photo: PhotoView | None = None) -> tuple[trimesh.Trimesh, MeshLevel]:
    """The mesh over the input camera's frustum box (fine network density, each point seen along the input
    camera's ray through it), its vertices coloured by ``config.colors`` when ``colored``; the field runs as
    ``runtime`` says (None: the default); ``mask``: the input's object mask (the ``silhouette`` level's target);
    ``photo``: the input photo (the ``photo`` colour rule reads it)."""
    eye = c2w[:3, 3].to(device)
    density_fn, _ = field_queries(model, enc, eye, runtime)
    mesh, level = source_mesh(density_fn, c2w, intr, near, far, config, None, device, mask)
    if colored and len(mesh.vertices):
        mesh.visual.vertex_colors = vertex_colors(
            config.colors, field_radiance(model, enc, runtime), mesh, eye, config.color_half_width,
            config.color_samples, config.chunk, device, photo, config.photo_fill)
    return mesh, level
