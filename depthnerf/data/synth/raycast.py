"""Ray-cast renderer of a :class:`~depthnerf.data.synth.primitives.SynthMesh`.

Rays are exactly those of :func:`depthnerf.data.cameras.camera_rays` (one per integer-centred pixel). A first-hit
engine (:mod:`depthnerf.data.synth.hits`: Intel Embree via embreex, or brute force in torch where embreex is
missing) only finds *which* triangle a ray hits first; the ray distance is then recomputed in float64 on that
triangle's plane, so z-depth is exact up to float64 rounding and reprojects between views without the float32
error of the traversal.

Outputs per view: RGB on a white background, z-depth (0 where no surface) and the mask, both from the centre ray
of each pixel (exact, never blended). Anti-aliasing is adaptive supersampling of RGB only: after the centre pass,
pixels whose part id / hit status differs from an 8-neighbour, or whose colour differs from one by more than
``edge_threshold``, get four more rays on a rotated grid (RGSS offsets); their colour is the mean of the five
samples (a box filter over the pixel). Smooth interiors have no sub-pixel detail (no textures), so their centre
colour already equals the box-filtered value.

Shading (fixed in the world frame, the same for every view and object, like SRN's renders): ambient from a
sky/ground hemisphere, two directional lights (Lambertian), a Blinn-Phong highlight, a Fresnel-weighted
reflection of a sky/ground gradient for glossy materials (glass, paint, chrome), and emission for lamps.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from jaxtyping import Bool, Float

from depthnerf.data.cameras import Intrinsics, pixel_directions
from depthnerf.data.synth.hits import first_hit_finder
from depthnerf.data.synth.primitives import SynthMesh

RGSS_OFFSETS = ((0.125, 0.375), (-0.375, 0.125), (-0.125, -0.375), (0.375, -0.125))
"""Sub-pixel (du, dv) offsets of the rotated-grid supersampling pattern."""


@dataclass(frozen=True)
class LightingConfig:
    """The fixed world-frame lighting rig (directions point *towards* the lights)."""

    key_direction: tuple[float, float, float] = (0.45, 0.3, 0.85)
    """Direction to the main light: above, front-left."""
    key_intensity: float = 0.62
    """Diffuse intensity of the main light."""
    fill_direction: tuple[float, float, float] = (-0.6, -0.55, 0.45)
    """Direction to the fill light: behind-right, lower."""
    fill_intensity: float = 0.28
    """Diffuse intensity of the fill light."""
    sky_ambient: float = 0.42
    """Ambient light on surfaces facing straight up."""
    ground_ambient: float = 0.22
    """Ambient light on surfaces facing straight down."""
    sky_reflection: float = 0.95
    """Brightness of the reflected sky (reflection directions pointing up)."""
    ground_reflection: float = 0.18
    """Brightness of the reflected ground (reflection directions pointing down)."""


@dataclass(frozen=True)
class SynthRenderConfig:
    """Settings of the synthetic-data renderer (``depthnerf synth``; the NeRF renderer's are
    :class:`depthnerf.render.config.RenderConfig`)."""

    lighting: LightingConfig = field(default_factory=LightingConfig)
    """The lighting rig."""
    antialias: bool = True
    """Adaptive RGSS supersampling of RGB at edges (depth and mask always come from the centre ray)."""
    edge_threshold: float = 0.03
    """Colour difference (max over channels) to an 8-neighbour that marks a pixel for supersampling."""
    background: float = 1.0
    """Background grey level (SRN: white)."""


@dataclass
class RenderedView:
    """One rendered view."""

    rgb: Float[np.ndarray, "H W 3"]
    """Colour in [0, 1] on the background."""
    depth: Float[np.ndarray, "H W"]
    """z-depth of the centre ray's hit, 0 where the ray misses."""
    mask: Bool[np.ndarray, "H W"]
    """True where the centre ray hits the object."""


@dataclass
class _Hits:
    """First hits of a batch of rays."""

    face: np.ndarray
    """Hit triangle, -1 for a miss."""
    t: np.ndarray
    """Ray distance along the unit direction (float64; inf for a miss)."""
    normal: np.ndarray
    """Interpolated shading normal, facing the ray origin (zeros for a miss)."""


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot product of two ``N x 3`` arrays (faster than ``(a * b).sum(1)``)."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def _normalize_rows(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.sqrt(_dot(v, v)), 1e-12)[:, None]


class Raycaster:
    """A first-hit engine over one mesh plus the per-face data the shader needs; ``engine``: ``auto``, ``embree``
    or ``torch`` (:mod:`depthnerf.data.synth.hits`)."""

    def __init__(self, mesh: SynthMesh, engine: str = "auto") -> None:
        self.mesh = mesh
        self._first_hits = first_hit_finder(mesh.vertices, mesh.faces, engine)
        self.engine = self._first_hits.engine
        tri = mesh.vertices[mesh.faces]
        e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
        d00, d01, d11 = _dot(e1, e1), _dot(e1, e2), _dot(e2, e2)
        inv = 1.0 / np.maximum(d00 * d11 - d01 * d01, 1e-30)
        # everything trace() needs per face in one row, so a hit costs one gather:
        # v0 0:3, e1 3:6, e2 6:9, plane normal 9:12, d00 d01 d11 inv 12:16, corner normals 16:25
        self._face_data = np.concatenate([tri[:, 0], e1, e2, np.cross(e1, e2), np.stack([d00, d01, d11, inv], 1),
                                          mesh.corner_normals.reshape(-1, 9)], axis=1)
        # per face: albedo 0:3, specular 3, shininess 4, reflect 5, emission 6
        mats = np.array([(*m.albedo, m.specular, m.shininess, m.reflect, m.emission) for m in mesh.materials],
                        dtype=np.float64)
        self._face_material = mats.reshape(-1, 7)[mesh.face_material]

    def trace(self, origins: np.ndarray, dirs: np.ndarray) -> _Hits:
        """First hit of each ray (unit ``dirs``), with the exact float64 distance on the hit triangle's plane."""
        face = self._first_hits(origins, dirs)
        hit = face >= 0
        f = face[hit]
        o, d = origins[hit], dirs[hit]
        fd = self._face_data[f]
        v0, e1, e2, n = fd[:, 0:3], fd[:, 3:6], fd[:, 6:9], fd[:, 9:12]
        d00, d01, d11, inv = fd[:, 12], fd[:, 13], fd[:, 14], fd[:, 15]
        denom = _dot(n, d)
        denom = np.where(np.abs(denom) < 1e-300, 1e-300, denom)
        t_hit = _dot(v0 - o, n) / denom
        w = o + t_hit[:, None] * d - v0
        d20, d21 = _dot(w, e1), _dot(w, e2)
        b1 = np.clip((d11 * d20 - d01 * d21) * inv, 0.0, 1.0)
        b2 = np.clip((d00 * d21 - d01 * d20) * inv, 0.0, 1.0)
        b0 = 1 - b1 - b2
        normal = _normalize_rows(b0[:, None] * fd[:, 16:19] + b1[:, None] * fd[:, 19:22] + b2[:, None] * fd[:, 22:25])
        normal *= -np.sign(_dot(normal, d) + 1e-12)[:, None]  # face the viewer
        t = np.full(len(face), np.inf)
        t[hit] = t_hit
        normals = np.zeros((len(face), 3))
        normals[hit] = normal
        return _Hits(face, t, normals)

    def shade(self, hits: _Hits, dirs: np.ndarray, cfg: SynthRenderConfig) -> np.ndarray:
        """Colour of each ray (background where it missed)."""
        light = cfg.lighting
        out = np.full((len(dirs), 3), cfg.background)
        hit = hits.face >= 0
        f, n, d = hits.face[hit], hits.normal[hit], dirs[hit]
        fm = self._face_material[f]
        albedo, ks, shin, f0, emit = fm[:, 0:3], fm[:, 3], fm[:, 4], fm[:, 5], fm[:, 6]
        ambient = light.ground_ambient + (light.sky_ambient - light.ground_ambient) * (0.5 + 0.5 * n[:, 2])
        lit = ambient.copy()
        spec = np.zeros(len(f))
        for direction, intensity in ((light.key_direction, light.key_intensity),
                                     (light.fill_direction, light.fill_intensity)):
            ldir = np.asarray(direction) / np.linalg.norm(direction)
            lit += intensity * np.clip(_dot(n, ldir[None]), 0.0, None)
            half = _normalize_rows(ldir[None] - d)
            spec += intensity * np.clip(_dot(n, half), 0.0, None) ** shin
        color = albedo * lit[:, None]
        dn = _dot(d, n)
        cos_v = np.clip(-dn, 0.0, 1.0)
        refl_dir_z = d[:, 2] - 2 * dn * n[:, 2]
        blend = np.clip((refl_dir_z + 0.15) / 0.5, 0.0, 1.0)
        env = light.ground_reflection + (light.sky_reflection - light.ground_reflection) * blend * blend * (3 - 2 * blend)
        fresnel = np.where(f0 > 0, f0 + (1 - f0) * (1 - cos_v) ** 5, 0.0)
        color = color * (1 - fresnel[:, None]) + (fresnel * env)[:, None]
        color += (ks * spec)[:, None]
        color = color * (1 - emit[:, None]) + albedo * emit[:, None]
        out[hit] = color
        return np.clip(out, 0.0, 1.0)


class PixelRays:
    """Camera-frame unit directions of every pixel centre and of the RGSS sub-samples, computed once per
    intrinsics with :func:`~depthnerf.data.cameras.pixel_directions`; :meth:`world` then applies a pose exactly
    as :func:`~depthnerf.data.cameras.camera_rays` does (``dirs @ R^T``), in float64."""

    def __init__(self, intr: Intrinsics) -> None:
        self.intr = intr
        self.centre = pixel_directions(intr).reshape(-1, 3).double().numpy()
        self.subsamples = [
            pixel_directions(Intrinsics(intr.focal, intr.cx - du, intr.cy - dv, intr.height, intr.width))
            .reshape(-1, 3).double().numpy()
            for du, dv in RGSS_OFFSETS
        ]

    @staticmethod
    def world(dirs_cam: np.ndarray, c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World-space origins and unit directions of camera-frame directions under pose ``c2w``."""
        c2w = np.asarray(c2w, dtype=np.float64)
        rot = c2w[:3, :3]  # dirs @ R^T, written out (no BLAS threads for a 3x3 product)
        dirs = dirs_cam[:, :1] * rot[:, 0] + dirs_cam[:, 1:2] * rot[:, 1] + dirs_cam[:, 2:3] * rot[:, 2]
        return np.broadcast_to(c2w[:3, 3], dirs.shape).copy(), dirs


def _edge_pixels(key: np.ndarray, luma: np.ndarray, threshold: float) -> np.ndarray:
    """Pixels whose key (part and material) differs from, or whose brightness differs by more than ``threshold``
    from, any 8-neighbour."""
    h, w = key.shape
    kp = np.pad(key, 1, mode="edge")
    lp = np.pad(luma, 1, mode="edge")
    edge = np.zeros((h, w), dtype=bool)
    for di, dj in ((0, 1), (1, 0), (1, 1), (1, -1)):  # each unordered neighbour pair once, marked on both ends
        a = (slice(1, 1 + h), slice(1, 1 + w))
        b = (slice(1 + di, 1 + di + h), slice(1 + dj, 1 + dj + w))
        diff = (kp[a] != kp[b]) | (np.abs(lp[a] - lp[b]) > threshold)
        edge |= diff
        shifted = np.zeros((h + 2, w + 2), dtype=bool)
        shifted[b] = diff
        edge |= shifted[a]
    return edge


def render_view(caster: Raycaster, c2w: np.ndarray, rays: PixelRays | Intrinsics,
                cfg: SynthRenderConfig) -> RenderedView:
    """Render RGB, z-depth and mask of ``caster.mesh`` seen by camera-to-world ``c2w`` (OpenCV axes).

    Pass a :class:`PixelRays` to reuse the per-pixel directions across views (an :class:`Intrinsics` works too).
    """
    rays = rays if isinstance(rays, PixelRays) else PixelRays(rays)
    c2w = np.asarray(c2w, dtype=np.float32)
    h, w = rays.intr.height, rays.intr.width
    origins, dirs = rays.world(rays.centre, c2w)
    hits = caster.trace(origins, dirs)
    rgb = caster.shade(hits, dirs, cfg).reshape(h, w, 3)
    mask = (hits.face >= 0).reshape(h, w)
    forward = c2w[:3, 2].astype(np.float64)
    z = np.where(mask.reshape(-1), _dot(dirs, forward[None]) * np.where(np.isfinite(hits.t), hits.t, 0.0), 0.0)
    if cfg.antialias:
        hit_face = np.maximum(hits.face, 0)
        key = np.where(hits.face >= 0, caster.mesh.face_part[hit_face] * 4096 + caster.mesh.face_material[hit_face],
                       -1).reshape(h, w)
        luma = 0.3 * rgb[..., 0] + 0.59 * rgb[..., 1] + 0.11 * rgb[..., 2]
        edge = _edge_pixels(key, luma, cfg.edge_threshold).reshape(-1)
        if edge.any():
            n_edge = int(edge.sum())
            sub = np.concatenate([s[edge] for s in rays.subsamples])
            so, sd = rays.world(sub, c2w)
            samples = caster.shade(caster.trace(so, sd), sd, cfg).reshape(len(rays.subsamples), n_edge, 3)
            flat = rgb.reshape(-1, 3)
            flat[edge] = (flat[edge] + samples.sum(0)) / (1 + len(rays.subsamples))
            rgb = flat.reshape(h, w, 3)
    return RenderedView(rgb.astype(np.float32), z.reshape(h, w).astype(np.float32), mask)
