"""The ``photo`` vertex colour rule (depthnerf.render.photo_colors) on scenes whose answer is known in closed form:
boxes seen by a camera on the -x axis through a linear colour ramp, so that the photo's colour at a point is a
formula of its position, visibility a slab test and the mirror image a sign change."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from depthnerf.data.cameras import Intrinsics, look_at
from depthnerf.render.photo_colors import (
    FACING_COS,
    GRAZING_COS,
    SPREAD_DATA_WEIGHT,
    PhotoView,
    bilinear,
    field_error,
    photo_blend,
    photo_samples,
    reflected,
    spread_colors,
)

EYE = np.array([-3.0, 0.0, 0.0])
FOCAL, SIZE = 100.0, 64
INTR = Intrinsics(focal=FOCAL, cx=(SIZE - 1) / 2, cy=(SIZE - 1) / 2, height=SIZE, width=SIZE)
FIELD = np.array([0.9, 0.1, 0.6])
"""The field's colour at every vertex: whatever the photo does not replace stays this."""


def ramp_image() -> np.ndarray:
    """RGB ``(j / 63, i / 63, 0.25)`` at pixel (row i, column j): linear, so bilinear sampling is exact."""
    i, j = np.mgrid[0:SIZE, 0:SIZE].astype(np.float64)
    return np.stack([j / (SIZE - 1), i / (SIZE - 1), np.full_like(i, 0.25)], -1)


def expected_photo(points: np.ndarray) -> np.ndarray:
    """The ramp at each point's projection, by hand: the camera at -3 x looks along +x with +z up, so image right
    is world -y, image down is world -z and the depth is ``x + 3``."""
    depth = points[:, 0] + 3.0
    u = FOCAL * -points[:, 1] / depth + INTR.cx
    v = FOCAL * -points[:, 2] / depth + INTR.cy
    return np.stack([u / (SIZE - 1), v / (SIZE - 1), np.full_like(u, 0.25)], -1)


def view(mask: np.ndarray | None = None, plane=None) -> PhotoView:
    c2w = look_at(torch.tensor(EYE, dtype=torch.float32)).double().numpy()
    return PhotoView(ramp_image(), np.ones((SIZE, SIZE), bool) if mask is None else mask, c2w, INTR,
                     None if plane is None else np.asarray(plane, dtype=np.float64))


def box(extent: float, centre=(0.0, 0.0, 0.0), splits: int = 3) -> trimesh.Trimesh:
    mesh = trimesh.creation.box(extents=(extent,) * 3)
    for _ in range(splits):
        mesh = mesh.subdivide()
    mesh.apply_translation(centre)
    return mesh


def face_rows(mesh: trimesh.Trimesh, axis: int, value: float, half: float, margin: float = 1e-3) -> np.ndarray:
    """Vertices on the box face ``x[axis] = value`` away from its edges (their normals are the face's)."""
    v = np.asarray(mesh.vertices)
    others = [k for k in range(3) if k != axis]
    return np.flatnonzero((np.abs(v[:, axis] - value) < 1e-9) & np.all(np.abs(v[:, others]) < half - margin, 1))


def blend(mesh: trimesh.Trimesh, photo: PhotoView) -> np.ndarray:
    return photo_blend(mesh, np.tile(FIELD, (len(mesh.vertices), 1)), photo).astype(np.float64)


def test_bilinear_is_exact_on_a_linear_image_and_clamps_at_the_border():
    image = ramp_image()
    uv = np.array([[0.0, 0.0], [10.25, 3.5], [62.9, 63.0], [31.5, 0.75]])
    assert np.allclose(bilinear(image, uv), np.stack([uv[:, 0] / 63, uv[:, 1] / 63, np.full(4, 0.25)], -1))
    outside = bilinear(image, np.array([[-5.0, 70.0], [80.0, -1.0]]))
    assert np.allclose(outside[:, :2], [[0.0, 1.0], [1.0, 0.0]])


def test_reflected_points_and_normals():
    plane = np.array([0.6, 0.8, 0.0, 0.5])
    x = np.random.default_rng(0).normal(size=(20, 3))
    image, image_dirs = reflected(x, x, plane)
    assert np.allclose(reflected(image, image, plane)[0], x)
    mid = (x + image) / 2
    assert np.allclose(mid @ plane[:3], plane[3])  # the midpoint lies on the plane
    assert np.allclose(image_dirs, image - reflected(np.zeros((1, 3)), np.zeros((1, 3)), plane)[0])


def test_the_near_face_takes_the_photo_and_the_hidden_faces_keep_the_field():
    mesh = box(1.0)
    rgb = blend(mesh, view())
    near = face_rows(mesh, 0, -0.5, 0.5)
    assert len(near) > 20
    assert np.allclose(rgb[near], expected_photo(np.asarray(mesh.vertices)[near]), atol=1e-5)
    hidden = np.concatenate([face_rows(mesh, 0, 0.5, 0.5)] +
                            [face_rows(mesh, a, s * 0.5, 0.5) for a in (1, 2) for s in (-1, 1)])
    assert np.allclose(rgb[hidden], FIELD, atol=1e-6)


def test_the_mirror_plane_colours_the_far_face_with_its_mirror_images_photo():
    mesh = box(1.0)
    rgb = blend(mesh, view(plane=[1.0, 0.0, 0.0, 0.0]))  # the plane x = 0: the far face mirrors onto the near one
    far = face_rows(mesh, 0, 0.5, 0.5)
    mirrored = np.asarray(mesh.vertices)[far] * [-1, 1, 1]
    assert np.allclose(rgb[far], expected_photo(mirrored), atol=1e-5)
    sides = np.concatenate([face_rows(mesh, a, s * 0.5, 0.5) for a in (1, 2) for s in (-1, 1)])
    assert np.allclose(rgb[sides], FIELD, atol=1e-6)  # they face away from the camera, and so do their images
    near = face_rows(mesh, 0, -0.5, 0.5)
    assert np.allclose(rgb[near], expected_photo(np.asarray(mesh.vertices)[near]), atol=1e-5)


def segment_meets_box(eye: np.ndarray, points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Slab test, one segment at a time: does the segment from ``eye`` to each point pass through the box?"""
    out = []
    for p in points:
        d = p - eye
        t0, t1 = 0.0, 1.0
        for k in range(3):
            if abs(d[k]) < 1e-12:
                if not lo[k] <= eye[k] <= hi[k]:
                    t0, t1 = 1.0, 0.0
                continue
            a, b = sorted(((lo[k] - eye[k]) / d[k], (hi[k] - eye[k]) / d[k]))
            t0, t1 = max(t0, a), min(t1, b)
        out.append(t0 <= t1)
    return np.array(out)


def test_a_part_in_front_hides_what_lies_behind_it_from_the_photo():
    centre, half = np.array([-1.5, 0.05, -0.1]), 0.15
    mesh = trimesh.util.concatenate([box(1.0), box(2 * half, centre, splits=1)])
    rgb = blend(mesh, view())
    near = face_rows(mesh, 0, -0.5, 0.5)
    points = np.asarray(mesh.vertices)[near]
    lo, hi = centre - half, centre + half
    behind = segment_meets_box(EYE, points, lo - 1e-3, hi + 1e-3)
    clear = ~segment_meets_box(EYE, points, lo + 1e-3, hi - 1e-3) & ~behind  # both agree: away from the edge
    assert behind.sum() > 5 and clear.sum() > 20
    assert np.allclose(rgb[near[behind & segment_meets_box(EYE, points, lo + 1e-3, hi - 1e-3)]], FIELD, atol=1e-6)
    assert np.allclose(rgb[near[clear]], expected_photo(points[clear]), atol=1e-5)


def test_the_shrunk_mask_decides_which_vertices_read_the_photo():
    mesh = box(1.0)
    mask = np.zeros((SIZE, SIZE), bool)
    mask[:, 32:] = True  # eroded by a pixel: columns >= 33 stay
    colours, weight = photo_samples(mesh, np.asarray(mesh.vertices), np.asarray(mesh.vertex_normals), view(mask))
    near = face_rows(mesh, 0, -0.5, 0.5)
    u = expected_photo(np.asarray(mesh.vertices)[near])[:, 0] * (SIZE - 1)
    on = np.rint(u) >= 33
    assert on.any() and (~on).any()
    assert np.all(weight[near[on]] == 1.0) and np.all(weight[near[~on]] == 0.0)


@pytest.mark.parametrize("tilt_deg", [0.0, 60.0, 72.0, 80.0, 88.0])
def test_grazing_surfaces_fade_to_the_field_colour(tilt_deg):
    """A square turned ``tilt_deg`` about the vertical axis: each vertex's weight is the ramp of its own cosine."""
    square = trimesh.creation.box(extents=(1e-3, 0.6, 0.6))
    for _ in range(3):
        square = square.subdivide()
    square.apply_transform(trimesh.transformations.rotation_matrix(np.radians(tilt_deg), [0, 0, 1]))
    v, n = np.asarray(square.vertices), np.asarray(square.vertex_normals)
    t = np.radians(tilt_deg)
    front = np.flatnonzero(n @ [-np.cos(t), -np.sin(t), 0.0] > 0.999)  # the face that was turned away from -x
    inside = (np.abs(v[front, 2]) < 0.3 - 1e-3) & (np.abs(v[front] @ [-np.sin(t), np.cos(t), 0.0]) < 0.3 - 1e-3)
    front = front[inside]
    assert len(front) > 10
    to_eye = EYE - v[front]
    cos = (n[front] * to_eye).sum(1) / np.linalg.norm(to_eye, axis=1)
    want = np.clip((cos - GRAZING_COS) / (FACING_COS - GRAZING_COS), 0, 1)
    _, weight = photo_samples(square, v[front], n[front], view())
    assert np.allclose(weight, want, atol=1e-9)
    rgb = blend(square, view())[front]
    assert np.allclose(rgb, want[:, None] * expected_photo(v[front]) + (1 - want[:, None]) * FIELD, atol=1e-5)


def test_an_empty_mesh_keeps_what_it_was_given():
    assert photo_blend(trimesh.Trimesh(), np.zeros((0, 3)), view()).shape == (0, 3)


def brute_force_spread(mesh: trimesh.Trimesh, colors, weight, prior, length) -> np.ndarray:
    """The energy of :func:`spread_colors` as a least-squares problem, one residual row per edge and per vertex term,
    solved densely: ``sqrt(a) (x_i - x_j)`` per edge, ``sqrt(K w_i) (x_i - c_i)`` and ``sqrt(eps) (x_i - p_i)``."""
    n = len(mesh.vertices)
    lengths = [np.linalg.norm(mesh.vertices[i] - mesh.vertices[j]) for i, j in mesh.edges_unique]
    eps = (np.mean(lengths) / length) ** 2
    rows, rhs = [], []
    for i, j in mesh.edges_unique:
        row = np.zeros(n)
        row[i], row[j] = 1.0, -1.0
        rows.append(row)
        rhs.append(np.zeros(3))
    for i in range(n):
        for scale, target in ((np.sqrt(SPREAD_DATA_WEIGHT * weight[i]), colors[i]), (np.sqrt(eps), prior[i])):
            row = np.zeros(n)
            row[i] = scale
            rows.append(row)
            rhs.append(scale * np.asarray(target))
    return np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)[0]


@pytest.mark.parametrize("length", [0.05, 0.3, 3.0])
def test_spread_colours_minimise_their_energy(length):
    mesh = trimesh.creation.icosphere(subdivisions=1)
    rng = np.random.default_rng(1)
    n = len(mesh.vertices)
    colors, prior = rng.uniform(size=(n, 3)), rng.uniform(size=(n, 3))
    weight = np.where(rng.uniform(size=n) < 0.3, rng.uniform(size=n), 0.0)
    got = spread_colors(mesh, colors, weight, prior, length)
    assert np.allclose(got, brute_force_spread(mesh, colors, weight, prior, length), atol=1e-8)


def test_spread_colours_reach_further_with_a_longer_length_and_leave_unseen_pieces_to_the_prior():
    seen, unseen = box(1.0, splits=2), box(0.3, (3.0, 0.0, 0.0), splits=1)  # two pieces, no edge between them
    mesh = trimesh.util.concatenate([seen, unseen])
    n_seen = len(seen.vertices)
    v = np.asarray(mesh.vertices)
    weight = np.where((np.arange(len(v)) < n_seen) & (v[:, 0] < -0.49), 1.0, 0.0)  # the first box's -x face
    colors, prior = np.tile([1.0, 0.0, 0.0], (len(v), 1)), np.tile([0.0, 0.0, 1.0], (len(v), 1))
    far = np.flatnonzero((np.arange(len(v)) < n_seen) & (v[:, 0] > 0.49))  # the first box's +x face
    reach = [spread_colors(mesh, colors, weight, prior, length)[far, 0].mean() for length in (0.1, 0.5, 2.0)]
    assert 0 < reach[0] < reach[1] < reach[2] < 1
    assert np.allclose(spread_colors(mesh, colors, weight, prior, 2.0)[n_seen:], [0.0, 0.0, 1.0], atol=1e-9)


def test_the_fill_colours_what_the_photo_does_not_see_from_what_it_sees():
    mesh = box(1.0)
    plain, filled = blend(mesh, view()), photo_blend(mesh, np.tile(FIELD, (len(mesh.vertices), 1)), view(), 5.0)
    near, far = face_rows(mesh, 0, -0.5, 0.5), face_rows(mesh, 0, 0.5, 0.5)
    assert np.allclose(filled[near], plain[near], atol=1e-5)  # seen: the photo either way
    photo_mean = plain[near].mean(0)
    assert np.abs(filled[far] - photo_mean).max() < 0.5 * np.abs(FIELD - photo_mean).max()


def test_a_field_that_matches_the_photo_where_it_sees_keeps_its_colours_elsewhere():
    mesh = box(1.0)
    field = expected_photo(np.asarray(mesh.vertices))  # the photo's colour law, extended to the whole box
    for fill in (0.0, 5.0):
        assert np.allclose(photo_blend(mesh, field, view(), fill), field, atol=1e-5)


def test_field_error_is_the_weighted_rms_colour_distance():
    field = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.5, 0.5, 0.5]])
    photo = np.array([[0.3, 0.4, 0.0], [1.0, 1.0, 1.0], [0.0, 0.0, 0.0]])
    assert field_error(field, photo, np.array([1.0, 1.0, 0.0])) == pytest.approx(np.sqrt(0.25 / 2))
    assert field_error(field, photo, np.array([0.0, 0.0, 2.0])) == pytest.approx(np.sqrt(0.75))
    assert field_error(field, photo, np.zeros(3)) == 0.0
