"""Procedural shapes and the renderer: normalisation, framing, variety, exact depth, anti-aliasing contract."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import trimesh

from depthnerf.data.cameras import Intrinsics, pixel_directions
from depthnerf.data.synth.cars import CAR_STYLES, build_car, sample_car
from depthnerf.data.synth.chairs import CHAIR_ARCHETYPES, CHAIR_DIAGONAL, build_chair, sample_chair
from depthnerf.data.synth.framing import SRN_INTRINSICS
from depthnerf.data.synth.generate import category_spec
from depthnerf.data.synth.primitives import box, cylinder, loft, superellipsoid
from depthnerf.data.synth.raycast import PixelRays, Raycaster, SynthRenderConfig, _edge_pixels, render_view
from depthnerf.data.synth.views import ViewConfig, eyes_from_angles, poses_from_eyes, spiral_eyes


def _side_pose(radius: float, elev_deg: float = 10.0, azim_deg: float = 90.0) -> np.ndarray:
    return poses_from_eyes(eyes_from_angles(radius, np.radians([elev_deg]), np.radians([azim_deg])))[0]


@pytest.mark.parametrize("part", [box((0.3, 0.2, 0.1)), cylinder((0, 0, 0), (0.1, 0.2, 0.3), 0.05),
                                  superellipsoid((0.3, 0.2, 0.1)), loft(np.stack(
                                      [np.stack([np.full(8, x), np.cos(np.arange(8) / 8 * 2 * np.pi),
                                                 np.sin(np.arange(8) / 8 * 2 * np.pi)], 1) for x in (0.0, 0.5, 1.0)]))])
def test_primitives_are_closed_and_face_outwards(part) -> None:
    mesh = trimesh.Trimesh(part.vertices, part.faces)
    mesh.merge_vertices()
    assert mesh.is_watertight and mesh.volume > 0  # positive volume: faces wind outwards
    tri = part.vertices[part.faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    agree = np.einsum("fcd,fd->fc", part.corner_normals, fn)
    assert (agree > 0).all()  # shading normals on the outer side of their face
    np.testing.assert_allclose(np.linalg.norm(part.corner_normals, axis=-1), 1.0, atol=1e-9)


def test_cars_are_srn_normalised() -> None:
    for k, style in enumerate(CAR_STYLES):
        mesh = build_car(sample_car(np.random.default_rng(k), style))
        lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
        assert np.linalg.norm(hi - lo) == pytest.approx(1.0)
        np.testing.assert_allclose((lo + hi) / 2, 0.0, atol=1e-12)
        length, width, height = hi - lo
        assert 0.82 < length < 0.95 and width < 0.6 * length and height < 0.55 * length, style
        # wheels touch the ground plane (lowest vertices sit below the origin, at the tyres)
        low = mesh.vertices[:, 2] < lo[2] + 1e-3
        assert np.abs(mesh.vertices[low, 0]).min() > 0.15 * length  # tyres at the axles, not in the middle


@pytest.mark.parametrize("category", ["cars", "chairs"])
def test_objects_fill_the_frame_like_srn(category: str) -> None:
    """View 64 at 128 px: cars span ~60-80% of the width, chairs ~50-70% of the height."""
    spec = category_spec(category)
    pose = poses_from_eyes(spiral_eyes(251, ViewConfig(radius=spec.radius)))[64]
    rays = PixelRays(SRN_INTRINSICS)
    for k in range(6):
        rng = np.random.default_rng(100 + k)
        mesh = build_car(sample_car(rng)) if category == "cars" else build_chair(sample_chair(rng))
        mask = render_view(Raycaster(mesh), pose, rays, SynthRenderConfig(antialias=False)).mask
        cols, rows = np.where(mask.any(0))[0], np.where(mask.any(1))[0]
        width, height = (np.ptp(cols) + 1) / 128, (np.ptp(rows) + 1) / 128
        if category == "cars":
            assert 0.6 <= width <= 0.8
        else:
            assert 0.5 <= height <= 0.7
            assert np.linalg.norm(np.ptp(mesh.vertices, 0)) == pytest.approx(CHAIR_DIAGONAL)
        assert not mask[0].any() and not mask[-1].any() and not mask[:, 0].any() and not mask[:, -1].any()


def _masks(builders, radius: float, size: int = 48) -> list[np.ndarray]:
    intr = SRN_INTRINSICS.resized(size, size)
    pose = _side_pose(radius, 12.0, 70.0)
    return [render_view(Raycaster(m), pose, intr, SynthRenderConfig(antialias=False)).mask for m in builders]


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / (a | b).sum())


def test_car_styles_have_clearly_different_silhouettes() -> None:
    cars = [build_car(sample_car(np.random.default_rng(7), s)) for s in CAR_STYLES]
    masks = _masks(cars, 1.3)
    for (i, a), (j, b) in itertools.combinations(enumerate(masks), 2):
        assert _iou(a, b) < 0.92, (CAR_STYLES[i], CAR_STYLES[j])  # measured max 0.89 (sedan vs sports)
    heights = {s: np.ptp(m.vertices[:, 2]) / np.ptp(m.vertices[:, 0]) for s, m in zip(CAR_STYLES, cars, strict=True)}
    assert heights["sports"] < heights["sedan"] < heights["suv"] < heights["van"]
    # same style, different seeds: still different shapes (proportions are sampled, not fixed)
    same = _masks([build_car(sample_car(np.random.default_rng(s), "sedan")) for s in (1, 2)], 1.3)
    assert _iou(*same) < 0.97


def test_chair_archetypes_have_clearly_different_silhouettes() -> None:
    chairs = [build_chair(sample_chair(np.random.default_rng(3), a)) for a in CHAIR_ARCHETYPES]
    masks = _masks(chairs, 2.0)
    for (i, a), (j, b) in itertools.combinations(enumerate(masks), 2):
        assert _iou(a, b) < 0.85, (CHAIR_ARCHETYPES[i], CHAIR_ARCHETYPES[j])


def test_sampling_covers_all_styles_and_parts() -> None:
    rng = np.random.default_rng(0)
    cars = {sample_car(rng).style for _ in range(200)}
    chairs = [sample_chair(rng) for _ in range(300)]
    assert cars == set(CAR_STYLES)
    assert {c.archetype for c in chairs} == set(CHAIR_ARCHETYPES)
    assert {c.legs for c in chairs} == {"four", "swivel", "sled", "pedestal", "panel"}
    assert {"solid", "curved", "slats", "ladder", "spindles", "splat", "office", "shell"} <= {c.back for c in chairs}
    assert {c.arms for c in chairs} == {"none", "posts", "office", "tube", "panel", "shell"}


@pytest.mark.parametrize("category", ["cars", "chairs"])
def test_depth_is_exact_on_the_mesh(category: str) -> None:
    """Back-projected depth pixels lie on the mesh surface (closest-point distance ~ float32 rounding)."""
    spec = category_spec(category)
    rng = np.random.default_rng(5)
    mesh = build_car(sample_car(rng)) if category == "cars" else build_chair(sample_chair(rng))
    intr = Intrinsics(40.0, 15.5, 15.5, 32, 32)
    pose = _side_pose(spec.radius, 30.0, 200.0)
    view = render_view(Raycaster(mesh), pose, intr, SynthRenderConfig())
    assert view.mask.sum() > 50
    assert ((view.depth > 0) == view.mask).all()
    cam = pixel_directions(intr, normalize=False).numpy()[view.mask] * view.depth[view.mask][:, None]
    world = cam @ pose[:3, :3].T.astype(np.float64) + pose[:3, 3]
    _, dist, _ = trimesh.proximity.closest_point(trimesh.Trimesh(mesh.vertices, mesh.faces, process=False), world)
    assert dist.max() < 1e-5


def test_background_is_white_and_antialiasing_only_touches_rgb() -> None:
    mesh = build_chair(sample_chair(np.random.default_rng(11), "dining"))
    intr = SRN_INTRINSICS.resized(64, 64)
    pose = _side_pose(2.0, 25.0, 40.0)
    aa = render_view(Raycaster(mesh), pose, intr, SynthRenderConfig(antialias=True))
    plain = render_view(Raycaster(mesh), pose, intr, SynthRenderConfig(antialias=False))
    np.testing.assert_array_equal(aa.depth, plain.depth)
    np.testing.assert_array_equal(aa.mask, plain.mask)
    changed = np.abs(aa.rgb - plain.rgb).max(-1) > 1e-6
    assert changed.any()  # edges were supersampled ...
    near = np.zeros_like(aa.mask)
    for di, dj in itertools.product((-1, 0, 1), repeat=2):
        near |= np.roll(np.roll(aa.mask, di, 0), dj, 1)
    assert (aa.rgb[~near] == 1.0).all()  # ... and the background away from the object stays pure white
    assert changed.mean() < 0.25  # adaptive: only a minority of pixels


def test_edge_pixels_are_those_differing_from_an_8_neighbour() -> None:
    """Against a loop over every pixel's 8 neighbours (inside the image): a pixel is an edge pixel when some
    neighbour has another key or a brightness more than the threshold away."""
    rng = np.random.default_rng(0)
    for h, w in ((1, 1), (1, 6), (5, 1), (4, 7), (7, 7)):
        key, luma, threshold = rng.integers(0, 3, (h, w)), rng.random((h, w)), 0.4
        expect = np.zeros((h, w), dtype=bool)
        for i, j, di, dj in itertools.product(range(h), range(w), (-1, 0, 1), (-1, 0, 1)):
            a, b = i + di, j + dj
            if (di or dj) and 0 <= a < h and 0 <= b < w:
                expect[i, j] |= key[a, b] != key[i, j] or abs(luma[a, b] - luma[i, j]) > threshold
        np.testing.assert_array_equal(_edge_pixels(key, luma, threshold), expect)
