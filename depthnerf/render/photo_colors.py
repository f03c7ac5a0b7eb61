"""Vertex colours from the input photo where the input camera sees the surface (the ``photo`` colour rule).

The field's colours are the renderer's: blurred, and darker than the photo even where the input camera looks
(docs/RESULTS.md, "Mesh vertex colours"). Where the input view itself shows a vertex, its true colour is in the
photo. :func:`photo_blend` keeps the field's colour ``c_field`` (``normal-ray``, :mod:`depthnerf.render.mesh_colors`)
and replaces it by the photo's where the photo sees the vertex:

``c = w_1 p(v) + (1 - w_1) (w_2 p(v') + (1 - w_2) c_field)``

- ``p(x)``: the photo's colour at the projection of world point ``x`` into the input camera (bilinear, pixel
  centres at integer coordinates as :mod:`depthnerf.data.cameras` states).
- ``w(x, n) = seen(x) * ramp(cos)``, with ``cos = n . (eye - x) / |eye - x|`` the cosine between the surface normal
  ``n`` and the direction to the camera centre ``eye``; ``ramp`` rises linearly from 0 at :data:`GRAZING_COS` to 1
  at :data:`FACING_COS`, so surfaces seen edge-on (one photo pixel smeared over many vertices) fade to the field's
  colour instead of ending in a seam.
- ``seen(x)`` is 1 when (a) ``x`` projects inside the photo onto the object's mask, shrunk by
  :data:`MASK_ERODE` pixels (silhouette pixels mix in the background), and (b) the first mesh triangle met by the
  ray from ``eye`` towards ``x`` lies no nearer than ``|x - eye| - tol``, ``tol`` = :data:`OCCLUSION_TOL` mean edge
  lengths (the vertex is not hidden behind another part of the mesh); else 0.
- ``v' = reflect(v)`` in the object's mirror plane, with the normal reflected too (``w_2``; 0 without a plane):
  a vertex on the far side of a mirror-symmetric object takes the colour of its mirror image on the near side.

Vertices that neither the photo nor its mirror sees (the top, front and back of a side view) keep ``c_field``, or
with a ``fill`` (:data:`PHOTO_FILL` by default in reconstruct) take the photo's colours spread over the surface from
the nearest seen vertices and fading into ``c_field`` (:func:`spread_colors`). How far they reach depends on how
wrong the field's colours proved where the photo sees: ``fill * sigma`` world units, ``sigma`` the RMS colour
distance between field and photo there (:func:`field_error`). A field that matches the photo keeps its colours.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import trimesh
from jaxtyping import Bool, Float
from scipy import ndimage, sparse
from scipy.sparse.linalg import splu

from depthnerf.data.cameras import Intrinsics, project, world_to_camera
from depthnerf.data.symmetry import reflect_dirs, reflect_points
from depthnerf.data.synth.hits import available_engine, first_hit_finder

PHOTO = "photo"
"""Colour rule: the input photo's colour where it sees the vertex or its mirror image, else ``normal-ray``."""
GRAZING_COS = 0.1
"""Below this cosine between normal and view direction a vertex takes no photo colour (module docstring)."""
FACING_COS = 0.35
"""At and above this cosine the photo's colour replaces the field's entirely."""
MASK_ERODE = 1
"""Pixels taken off the object's mask before a vertex may read the photo (the silhouette mixes in background)."""
OCCLUSION_TOL = 1.5
"""How far (in mean mesh edge lengths) a first hit may lie in front of a vertex that still counts as seen."""
PHOTO_FILL = 0.3
"""Default ``fill`` of :func:`photo_blend`: the photo's colours reach ``0.3 sigma`` world units into what it does not
see (docs/RESULTS.md, "Mesh vertex colours", measures 0 to 1)."""
SPREAD_DATA_WEIGHT = 100.0
""":func:`spread_colors`: the weight of a seen vertex's photo colour, against 1 per mesh edge of smoothness."""


@dataclass(frozen=True)
class PhotoView:
    """The input photo as the mesh's colours read it: what the camera saw, where it stood, and the object's plane."""

    image: Float[np.ndarray, "H W 3"]
    """RGB in [0, 1], as the encoder saw it."""
    mask: Bool[np.ndarray, "H W"]
    """The object's pixels."""
    c2w: Float[np.ndarray, "4 4"]
    """Camera-to-world pose of the photo (OpenCV axes)."""
    intr: Intrinsics
    """Its intrinsics, at the image's resolution."""
    plane: Float[np.ndarray, " 4"] | None = None
    """The object's mirror plane ``(n, d)`` (``n . x = d``, unit ``n``) in the world frame; None or a zero row:
    none."""


def photo_samples(mesh: trimesh.Trimesh, points: Float[np.ndarray, "N 3"], normals: Float[np.ndarray, "N 3"],
                  view: PhotoView) -> tuple[Float[np.ndarray, "N 3"], Float[np.ndarray, " N"]]:
    """``(p(x), w(x, n))`` of each point (module docstring): the photo's colour at its projection and the weight
    that colour gets (0 where the photo does not see the point)."""
    points = np.asarray(points, dtype=np.float64)
    eye = np.asarray(view.c2w, dtype=np.float64)[:3, 3]
    to_eye = eye - points
    dist = np.linalg.norm(to_eye, axis=1)
    cos = (np.asarray(normals, dtype=np.float64) * to_eye).sum(1) / np.maximum(dist, 1e-12)
    weight = np.clip((cos - GRAZING_COS) / (FACING_COS - GRAZING_COS), 0.0, 1.0)
    cam = world_to_camera(torch.as_tensor(points), torch.as_tensor(np.asarray(view.c2w, dtype=np.float64)))
    uv = project(cam, view.intr.focal, (view.intr.cx, view.intr.cy)).numpy()
    h, w = view.mask.shape
    col, row = np.rint(uv[:, 0]).astype(np.int64), np.rint(uv[:, 1]).astype(np.int64)
    inside = (cam[:, 2].numpy() > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
    core = ndimage.binary_erosion(view.mask, iterations=MASK_ERODE) if MASK_ERODE else view.mask
    on_object = np.zeros(len(points), dtype=bool)
    on_object[inside] = core[row[inside], col[inside]]
    candidates = np.flatnonzero(on_object & (weight > 0))
    seen = np.zeros(len(points), dtype=bool)
    if len(candidates):
        seen[candidates] = unoccluded(mesh, eye, points[candidates], dist[candidates])
    return bilinear(view.image, uv), np.where(seen, weight, 0.0)


def unoccluded(mesh: trimesh.Trimesh, eye: Float[np.ndarray, " 3"], points: Float[np.ndarray, "N 3"],
               dist: Float[np.ndarray, " N"]) -> Bool[np.ndarray, " N"]:
    """Whether the first triangle of ``mesh`` on the ray from ``eye`` towards each point lies no nearer than the
    point's distance ``dist`` less :data:`OCCLUSION_TOL` mean edge lengths (a ray that meets nothing: False)."""
    vertices, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces)
    dirs = (points - eye) / np.maximum(dist, 1e-12)[:, None]
    origins = np.broadcast_to(eye, points.shape).copy()
    face = first_hit_finder(vertices, faces, available_engine())(origins, dirs)  # the same hits, up to ties
    hit = face >= 0
    a, b, c = (vertices[faces[face[hit]]][:, k] for k in range(3))
    e1, e2, s = b - a, c - a, origins[hit] - a
    q = np.cross(s, e1)
    t = (e2 * q).sum(1) / (e1 * np.cross(dirs[hit], e2)).sum(1)  # Moller-Trumbore distance to the hit
    tol = OCCLUSION_TOL * float(mesh.edges_unique_length.mean())
    out = np.zeros(len(points), dtype=bool)
    out[hit] = t >= dist[hit] - tol
    return out


def bilinear(image: Float[np.ndarray, "H W 3"], uv: Float[np.ndarray, "N 2"]) -> Float[np.ndarray, "N 3"]:
    """``image`` at continuous pixel coordinates ``(u, v)`` (pixel ``(i, j)`` centred at ``(j, i)``), bilinear,
    clamped to the border (``scipy.ndimage.map_coordinates``, order 1)."""
    rows_cols = [np.asarray(uv[:, 1], dtype=np.float64), np.asarray(uv[:, 0], dtype=np.float64)]
    return np.stack([ndimage.map_coordinates(np.asarray(image[..., c], dtype=np.float64), rows_cols, order=1,
                                             mode="nearest") for c in range(image.shape[-1])], axis=-1)


def reflected(points: Float[np.ndarray, "N 3"], normals: Float[np.ndarray, "N 3"], plane: Float[np.ndarray, " 4"]
              ) -> tuple[Float[np.ndarray, "N 3"], Float[np.ndarray, "N 3"]]:
    """Mirror images of points and their normals in ``plane`` (:func:`~depthnerf.data.symmetry.reflect_points`,
    :func:`~depthnerf.data.symmetry.reflect_dirs`)."""
    p = torch.tensor(plane, dtype=torch.float64)[None]  # copies: trimesh's arrays are read-only
    return (reflect_points(torch.tensor(points, dtype=torch.float64)[None], p)[0].numpy(),
            reflect_dirs(torch.tensor(normals, dtype=torch.float64)[None], p)[0].numpy())


def photo_blend(mesh: trimesh.Trimesh, field_rgb: Float[np.ndarray, "N 3"], view: PhotoView, fill: float = 0.0
                ) -> Float[np.ndarray, "N 3"]:
    """The ``photo`` rule's colours of ``mesh``'s vertices (module docstring) from the field's ``field_rgb``; with
    ``fill > 0`` the vertices the photo does not see take the photo's colours spread over the surface
    (:func:`spread_colors`) into the field's, over ``fill * sigma`` world units (:func:`field_error`)."""
    field = np.asarray(field_rgb, dtype=np.float64)
    if len(mesh.faces) == 0:
        return field.astype(np.float32)
    vertices, normals = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.vertex_normals)
    direct, w_direct = photo_samples(mesh, vertices, normals, view)
    mirrored, w_mirror = np.zeros_like(direct), np.zeros_like(w_direct)
    plane = None if view.plane is None else np.asarray(view.plane, dtype=np.float64)
    if plane is not None and np.abs(plane[:3]).sum() > 0:
        mirrored, w_mirror = photo_samples(mesh, *reflected(vertices, normals, plane), view)
    # c = w_1 p(v) + (1 - w_1) (w_2 p(v') + (1 - w_2) c_field) = k photo + (1 - k) c_field
    seen = w_direct + (1 - w_direct) * w_mirror
    photo = (w_direct[:, None] * direct + ((1 - w_direct) * w_mirror)[:, None] * mirrored) / \
        np.maximum(seen, 1e-12)[:, None]
    rest = field
    length = fill * field_error(field, photo, seen) if fill > 0 else 0.0
    if length > 0:
        rest = spread_colors(mesh, photo, seen, field, length)
    return (seen[:, None] * photo + (1 - seen[:, None]) * rest).astype(np.float32)


def field_error(field: Float[np.ndarray, "N 3"], photo: Float[np.ndarray, "N 3"], seen: Float[np.ndarray, " N"]
                ) -> float:
    """``sigma``: the root of the ``seen``-weighted mean squared RGB distance between the field's and the photo's
    colours where the photo sees the surface (0 where it sees none). How far the field's own colours can be trusted
    where the photo does not see: the fill of :func:`photo_blend` reaches ``fill * sigma`` world units, so a field
    whose colours match the photo keeps its own."""
    total = float(seen.sum())
    if total <= 0:
        return 0.0
    return float(np.sqrt((seen * ((field - photo) ** 2).sum(1)).sum() / total))


def spread_colors(mesh: trimesh.Trimesh, colors: Float[np.ndarray, "N 3"], weight: Float[np.ndarray, " N"],
                  prior: Float[np.ndarray, "N 3"], length: float) -> Float[np.ndarray, "N 3"]:
    """The vertex colours ``x`` that minimise

    ``sum over mesh edges (i, j) |x_i - x_j|^2 + sum over vertices (K w_i |x_i - c_i|^2 + eps |x_i - prior_i|^2)``

    with ``K`` = :data:`SPREAD_DATA_WEIGHT` and ``eps = (h / length)^2``, ``h`` the mean edge length: the colours
    ``c`` (weight ``w``, 0 = unknown) spread over the surface into the unknown vertices and fade into ``prior`` over
    about ``length`` world units (the decay length of the edge chain's solution, ``h / sqrt(eps)``). A piece of the
    mesh without a known vertex takes ``prior``. One sparse symmetric positive definite solve (``L + diag(K w +
    eps)``, ``L`` the graph Laplacian), three right-hand sides."""
    n = len(mesh.vertices)
    edges = np.asarray(mesh.edges_unique)
    eps = (float(mesh.edges_unique_length.mean()) / length) ** 2
    adjacency = sparse.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    adjacency = (adjacency + adjacency.T).tocsr()
    degree = np.asarray(adjacency.sum(axis=1)).ravel()
    data = SPREAD_DATA_WEIGHT * np.asarray(weight, dtype=np.float64)
    system = (sparse.diags(degree + data + eps) - adjacency).tocsc()
    rhs = data[:, None] * np.asarray(colors, dtype=np.float64) + eps * np.asarray(prior, dtype=np.float64)
    return splu(system).solve(rhs)
