"""Mesh building blocks for the procedural objects: parts with shading normals, materials, and the assembler.

A :class:`Part` is a triangle soup with *corner normals*: every face carries its own three shading normals, so one
part can be smooth where it should be (the side of a cylinder, a car body) and creased where it should be (box
edges, cylinder caps) without shared-vertex bookkeeping. The renderer interpolates corner normals with the hit's
barycentric coordinates. Every primitive is built in a local frame and placed with :meth:`Part.transformed`.

:class:`MeshBuilder` collects parts with a :class:`Material` each (or one material per face), numbers the parts
(the renderer anti-aliases across part boundaries), and returns a :class:`SynthMesh` normalised so that its
bounding box is centred at the origin with a chosen diagonal (ShapeNet-style normalisation). Objects are built
in world axes: +x is the object's front, +y its left, +z up.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from jaxtyping import Float, Int

FloatArray = np.ndarray


@dataclass(frozen=True)
class Material:
    """Surface appearance used by the ray-cast shader (Lambertian + ambient, optional gloss and emission)."""

    name: str
    """Material family (paint, glass, rubber, wood, fabric, metal, plastic, light, ...), kept in the card."""
    albedo: tuple[float, float, float]
    """Diffuse colour in [0, 1] (display values, no gamma)."""
    specular: float = 0.0
    """Strength of the Blinn-Phong highlight."""
    shininess: float = 32.0
    """Blinn-Phong exponent."""
    reflect: float = 0.0
    """Strength of the Fresnel-weighted reflection of the sky/ground gradient (glass, glossy paint, chrome)."""
    emission: float = 0.0
    """Fraction of the albedo shown regardless of lighting (head/tail lights)."""


@dataclass
class Part:
    """A triangle soup with per-face corner normals (one primitive, not yet given a material)."""

    vertices: Float[np.ndarray, "N 3"]
    """Vertex positions."""
    faces: Int[np.ndarray, "F 3"]
    """Vertex indices of each triangle (counter-clockwise seen from outside)."""
    corner_normals: Float[np.ndarray, "F 3 3"]
    """Unit shading normal at each corner of each face."""

    def transformed(self, rotation: FloatArray | None = None, translation: FloatArray | None = None,
                    scale: FloatArray | float = 1.0) -> Part:
        """``x -> R (s * x) + t`` (``scale`` may be per-axis; normals transform with the inverse transpose)."""
        rot = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)
        trans = np.zeros(3) if translation is None else np.asarray(translation, dtype=np.float64)
        s = np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,))
        verts = (self.vertices * s) @ rot.T + trans
        normals = _unit((self.corner_normals / s) @ rot.T)
        faces = self.faces if np.prod(s) > 0 else self.faces[:, ::-1]
        normals = normals if np.prod(s) > 0 else normals[:, ::-1]
        return Part(verts, faces.copy(), normals)


@dataclass
class SynthMesh:
    """An assembled object: triangles, shading normals, and a material and part id per face."""

    vertices: Float[np.ndarray, "N 3"]
    """Vertex positions in world coordinates."""
    faces: Int[np.ndarray, "F 3"]
    """Vertex indices of each triangle."""
    corner_normals: Float[np.ndarray, "F 3 3"]
    """Unit shading normal at each face corner."""
    face_material: Int[np.ndarray, "F"]  # noqa: F821, UP037
    """Index into ``materials`` for every face."""
    face_part: Int[np.ndarray, "F"]  # noqa: F821, UP037
    """Part number of every face (edges between parts are anti-aliased)."""
    materials: list[Material]
    """The materials used by this object."""

    def to_trimesh(self) -> trimesh.Trimesh:
        """The mesh as a ``trimesh.Trimesh`` with per-face colours (what ``mesh.ply`` stores)."""
        albedo = np.array([m.albedo for m in self.materials], dtype=np.float64).reshape(-1, 3)
        rgb = np.round(np.clip(albedo[self.face_material], 0, 1) * 255).astype(np.uint8)
        colors = np.concatenate([rgb, np.full((len(rgb), 1), 255, np.uint8)], axis=1)
        return trimesh.Trimesh(self.vertices, self.faces, face_colors=colors, process=False)


class MeshBuilder:
    """Accumulates parts with materials and produces a normalised :class:`SynthMesh`."""

    def __init__(self) -> None:
        self._parts: list[tuple[Part, np.ndarray]] = []
        self._materials: list[Material] = []

    def _material_index(self, material: Material) -> int:
        if material not in self._materials:
            self._materials.append(material)
        return self._materials.index(material)

    def add(self, part: Part, material: Material | list[Material], face_choice: np.ndarray | None = None) -> None:
        """Add a part in one material, or with ``face_choice[f]`` indexing a list of materials per face."""
        if isinstance(material, Material):
            ids = np.full(len(part.faces), self._material_index(material), dtype=np.int64)
        else:
            table = np.array([self._material_index(m) for m in material], dtype=np.int64)
            ids = table[np.asarray(face_choice, dtype=np.int64)]
        self._parts.append((part, ids))

    def build(self, diagonal: float) -> SynthMesh:
        """Concatenate the parts, centre the bounding box at the origin and scale its diagonal to ``diagonal``."""
        verts, faces, normals, mats, part_ids, offset = [], [], [], [], [], 0
        for number, (part, ids) in enumerate(self._parts):
            verts.append(part.vertices)
            faces.append(part.faces + offset)
            normals.append(part.corner_normals)
            mats.append(ids)
            part_ids.append(np.full(len(part.faces), number, dtype=np.int64))
            offset += len(part.vertices)
        vertices = np.concatenate(verts)
        lo, hi = vertices.min(0), vertices.max(0)
        vertices = (vertices - (lo + hi) / 2) * (diagonal / np.linalg.norm(hi - lo))
        return SynthMesh(vertices, np.concatenate(faces), np.concatenate(normals), np.concatenate(mats),
                         np.concatenate(part_ids), list(self._materials))


def _unit(v: FloatArray) -> FloatArray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def frame_from_axis(axis: FloatArray) -> FloatArray:
    """A rotation whose third column is the unit ``axis`` (used to orient lathes and beams)."""
    z = _unit(np.asarray(axis, dtype=np.float64))
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = _unit(np.cross(helper, z))
    return np.stack([x, np.cross(z, x), z], axis=1)


def flat_part(vertices: FloatArray, faces: np.ndarray) -> Part:
    """A part shaded flat: every corner gets its face normal."""
    tri = vertices[faces]
    n = _unit(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]))
    return Part(vertices, faces, np.repeat(n[:, None], 3, axis=1))


def box(size: FloatArray, center: FloatArray = (0, 0, 0), rotation: FloatArray | None = None) -> Part:
    """An axis-aligned (then rotated) box with flat faces."""
    mesh = trimesh.creation.box(extents=np.asarray(size, dtype=np.float64))
    verts = np.asarray(mesh.vertices)[np.asarray(mesh.faces)].reshape(-1, 3)
    part = flat_part(verts, np.arange(len(verts)).reshape(-1, 3))
    return part.transformed(rotation, np.asarray(center, dtype=np.float64))


def beam(p0: FloatArray, p1: FloatArray, width: float, depth: float | None = None,
         up: FloatArray = (0, 0, 1)) -> Part:
    """A box of cross-section ``width x depth`` running from ``p0`` to ``p1`` (roll fixed by ``up``)."""
    p0, p1 = np.asarray(p0, dtype=np.float64), np.asarray(p1, dtype=np.float64)
    axis = p1 - p0
    z = _unit(axis)
    up = np.asarray(up, dtype=np.float64)
    if abs(np.dot(_unit(up), z)) > 0.99:
        up = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = _unit(np.cross(up, z))
    rot = np.stack([x, np.cross(z, x), z], axis=1)
    return box((width, width if depth is None else depth, np.linalg.norm(axis)), (p0 + p1) / 2, rot)


def lathe(profile: FloatArray, segments: int = 24) -> Part:
    """Revolve a polyline of ``(radius, z)`` points about the local z axis.

    Shading is smooth around the axis and flat along the profile (each profile segment keeps its own 2D normal),
    so a profile with a corner gives a crease there (cylinder caps, tyre shoulders). The profile runs so that its
    outside is on the right when walking along it (e.g. bottom centre -> rim -> top centre).
    """
    prof = np.asarray(profile, dtype=np.float64)
    ang = np.linspace(0.0, 2 * np.pi, segments + 1)[:-1]
    cos, sin = np.cos(ang), np.sin(ang)
    seg = prof[1:] - prof[:-1]
    seg_n = _unit(np.stack([seg[:, 1], -seg[:, 0]], axis=1))  # (dr, dz) rotated clockwise = outward
    k = np.arange(segments)
    k1 = (k + 1) % segments
    verts, faces, normals, base = [], [], [], 0
    for j in range(len(seg)):
        (r0, z0), (r1, z1) = prof[j], prof[j + 1]
        ring0 = np.stack([r0 * cos, r0 * sin, np.full(segments, z0)], axis=1)
        ring1 = np.stack([r1 * cos, r1 * sin, np.full(segments, z1)], axis=1)
        nr, nz = seg_n[j]
        ring_n = np.stack([nr * cos, nr * sin, np.full(segments, nz)], axis=1)
        verts.append(np.concatenate([ring0, ring1]))
        a, b, c, d = base + k, base + k1, base + segments + k1, base + segments + k
        faces.append(np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]))
        normals.append(np.concatenate([ring_n, ring_n]))
        base += 2 * segments
    v = np.concatenate(verts)
    f = np.concatenate(faces)
    vn = np.concatenate(normals)
    tri = v[f]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    f = f[area > 1e-14]
    return Part(v, f, _unit(vn[f]))


def cylinder(p0: FloatArray, p1: FloatArray, radius: float, segments: int = 16,
             radius1: float | None = None) -> Part:
    """A capped (possibly tapered) cylinder from ``p0`` to ``p1``."""
    p0, p1 = np.asarray(p0, dtype=np.float64), np.asarray(p1, dtype=np.float64)
    length = np.linalg.norm(p1 - p0)
    r1 = radius if radius1 is None else radius1
    part = lathe([(0.0, 0.0), (radius, 0.0), (r1, length), (0.0, length)], segments)
    return part.transformed(frame_from_axis(p1 - p0), p0)


def superellipsoid(half: FloatArray, center: FloatArray = (0, 0, 0), e_vertical: float = 0.3,
                   e_horizontal: float = 0.3, rows: int = 12, cols: int = 24,
                   rotation: FloatArray | None = None) -> Part:
    """A superellipsoid with half-extents ``half``: exponents near 0 give a rounded box, 1 an ellipsoid.

    Normals are the analytic gradient of the implicit function, so the rounded edges shade smoothly.
    """
    a, b, c = (float(h) for h in half)
    eta = np.linspace(-np.pi / 2, np.pi / 2, rows + 1)
    omega = np.linspace(-np.pi, np.pi, cols + 1)[:-1]
    ce, se = np.cos(eta)[:, None], np.sin(eta)[:, None]
    ce[0], ce[-1] = 0.0, 0.0  # exact poles (cos(pi/2) is 6e-17, which a small exponent would inflate)
    cw, sw = np.cos(omega)[None], np.sin(omega)[None]

    def spow(x: FloatArray, p: float) -> FloatArray:
        return np.sign(x) * np.abs(x) ** p

    x = a * spow(ce, e_vertical) * spow(cw, e_horizontal)
    y = b * spow(ce, e_vertical) * spow(sw, e_horizontal)
    z = c * spow(se, e_vertical) * np.ones_like(cw)
    # gradient of the implicit function (up to a positive factor per point)
    nx = spow(ce, 2 - e_vertical) * spow(cw, 2 - e_horizontal) / a
    ny = spow(ce, 2 - e_vertical) * spow(sw, 2 - e_horizontal) / b
    nz = spow(se, 2 - e_vertical) * np.ones_like(cw) / c
    pole = np.zeros_like(nx, dtype=bool)
    pole[0], pole[-1] = True, True
    nx, ny = np.where(pole, 0.0, nx), np.where(pole, 0.0, ny)
    verts = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    vn = _unit(np.stack([nx, ny, nz], axis=-1).reshape(-1, 3))
    i, j = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    j1 = (j + 1) % cols
    a0, b0, c0, d0 = i * cols + j, i * cols + j1, (i + 1) * cols + j1, (i + 1) * cols + j
    faces = np.concatenate([np.stack([a0, b0, c0], -1).reshape(-1, 3), np.stack([a0, c0, d0], -1).reshape(-1, 3)])
    tri = verts[faces]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    faces = faces[area > 1e-14]
    return Part(verts, faces, vn[faces]).transformed(rotation, np.asarray(center, dtype=np.float64))


def loft(rings: FloatArray, smooth: bool = True, cap: bool = True) -> Part:
    """A closed tube through ``S`` cross-section rings of ``K`` points each (``rings`` is ``S x K x 3``).

    Rings must run counter-clockwise as seen from beyond the last ring looking back (so faces point outwards).
    Smooth normals come from finite differences on the ring grid; the end caps are flat fans about the centroid.
    """
    return loft_indexed(rings, smooth, cap)[0]


def loft_indexed(rings: FloatArray, smooth: bool = True, cap: bool = True) -> tuple[Part, np.ndarray, np.ndarray]:
    """:func:`loft` plus, per face, the station interval ``i`` (ring ``i`` to ``i+1``) and ring segment ``j``
    (point ``j`` to ``j+1``) it spans; cap faces get ``-1`` for both (used to colour windows, pillars, trims)."""
    rings = np.asarray(rings, dtype=np.float64)
    n_st, k = rings.shape[:2]
    verts = rings.reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n_st - 1), np.arange(k), indexing="ij")
    j1 = (j + 1) % k
    a, b, c, d = i * k + j, i * k + j1, (i + 1) * k + j1, (i + 1) * k + j
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    st_idx, ring_idx = np.tile(i.reshape(-1), 2), np.tile(j.reshape(-1), 2)
    tri = verts[faces]
    fn = _unit(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]))
    normals = np.repeat(fn[:, None], 3, axis=1)
    if smooth:
        along = np.gradient(rings, axis=0)
        around = np.roll(rings, -1, axis=1) - np.roll(rings, 1, axis=1)
        vn = _unit(np.cross(around, along)).reshape(-1, 3)[faces]
        good = np.einsum("fcd,fd->fc", vn, fn) > 0.2  # degenerate grid spots fall back to flat
        normals = np.where(good[..., None], vn, normals)
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    keep = area > 1e-14
    parts = [Part(verts, faces[keep], normals[keep])]
    st_idx, ring_idx = st_idx[keep], ring_idx[keep]
    if cap:
        for ring, flip in ((rings[0], True), (rings[-1], False)):
            v = np.concatenate([ring, ring.mean(0)[None]])
            jj = np.arange(k)
            f = np.stack([np.full(k, k), jj, (jj + 1) % k], 1)
            parts.append(flat_part(v, f[:, ::-1] if flip else f))
        st_idx = np.concatenate([st_idx, np.full(2 * k, -1)])
        ring_idx = np.concatenate([ring_idx, np.full(2 * k, -1)])
    return merge(parts), st_idx, ring_idx


def prism(outline: FloatArray, z0: float, z1: float, smooth_sides: bool = True) -> Part:
    """Extrude a convex, counter-clockwise 2D ``outline`` (``K x 2``, in the xy plane) from ``z0`` to ``z1``."""
    out = np.asarray(outline, dtype=np.float64)
    lo = np.concatenate([out, np.full((len(out), 1), z0)], 1)
    hi = np.concatenate([out, np.full((len(out), 1), z1)], 1)
    side = loft(np.stack([lo, hi]), smooth=smooth_sides, cap=True)
    return side


def merge(parts: list[Part]) -> Part:
    """Concatenate parts into one (same material, same part number)."""
    verts, faces, normals, offset = [], [], [], 0
    for p in parts:
        verts.append(p.vertices)
        faces.append(p.faces + offset)
        normals.append(p.corner_normals)
        offset += len(p.vertices)
    return Part(np.concatenate(verts), np.concatenate(faces), np.concatenate(normals))


def superellipse_outline(half_x: float, half_y: float, exponent: float = 4.0, points: int = 32,
                         front_scale: float = 1.0) -> FloatArray:
    """Counter-clockwise outline of a superellipse ``|x/a|^n + |y/b|^n = 1``; ``front_scale`` widens the +x half."""
    t = np.linspace(0, 2 * np.pi, points + 1)[:-1]
    c, s = np.cos(t), np.sin(t)
    x = half_x * np.sign(c) * np.abs(c) ** (2 / exponent)
    y = half_y * np.sign(s) * np.abs(s) ** (2 / exponent)
    y = y * np.where(x > 0, 1 + (front_scale - 1) * x / half_x, 1.0)
    return np.stack([x, y], 1)
