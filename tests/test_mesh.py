"""Mesh extraction (grid layout, marching cubes of analytic densities) and Chamfer-L1 / F-score closed forms."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch
import trimesh

from depthnerf.data.cameras import Intrinsics, look_at, project, world_to_camera
from depthnerf.data.mesh_file import read_mesh
from depthnerf.errors import DepthnerfError
from depthnerf.eval.geometry_metrics import (
    GeometryConfig,
    chamfer_l1,
    fscore,
    geometry_metrics,
    nearest_distances,
    sample_surface,
    summarize_geometry,
)
from depthnerf.render.mesh import CameraGrid, MeshConfig, extract_mesh, keep_pieces, sample_density

INTR = Intrinsics(focal=131.25, cx=63.5, cy=63.5, height=128, width=128)  # SRN cars at 128x128
C2W = look_at(torch.tensor([1.1, -0.5, 0.6]))
CENTRE = torch.tensor([0.05, -0.03, 0.02])


def sphere_density(radius: float, centre: torch.Tensor = CENTRE, level: float = 20.0):
    """Smooth density equal to ``level`` exactly on the sphere, higher inside."""
    return lambda p: 2 * level * torch.sigmoid((radius - (p - centre).norm(dim=-1)) / 0.02)


def test_layout_has_cube_voxels_covering_the_box():
    grid = CameraGrid(torch.eye(4), (-1.0, -0.5, 0.8), (1.0, 0.5, 1.6))
    shape, step, origin = grid.layout(21)
    assert step == pytest.approx(0.1) and shape == (21, 11, 9)
    far = origin + (np.array(shape) - 1) * step
    assert np.all(origin <= np.array(grid.lo) + 1e-9) and np.all(far >= np.array(grid.hi) - 1e-9)
    with pytest.raises(DepthnerfError):
        grid.layout(1)
    with pytest.raises(DepthnerfError):
        CameraGrid(torch.eye(4), (0.0, 0.0, 1.0), (1.0, 1.0, 1.0))


def test_grid_is_centred_on_a_box_its_step_does_not_divide():
    """A 1 x 0.45 x 0.3 box at resolution 11: step 0.1, 11 x 6 x 4 samples; the y samples span 0.5, overhanging
    the box by 0.025 on each side (first sample at -0.025), x and z fit exactly."""
    shape, step, origin = CameraGrid(torch.eye(4), (0.0, 0.0, 0.0), (1.0, 0.45, 0.3)).layout(11)
    assert shape == (11, 6, 4) and step == pytest.approx(0.1)
    np.testing.assert_allclose(origin, [0.0, -0.025, 0.0], atol=1e-12)


def test_frustum_box_contains_what_the_image_sees():
    grid = CameraGrid.from_frustum(C2W, INTR, 0.8, 1.8)
    assert grid.lo[2] == 0.8 and grid.hi[2] == 1.8
    # the pixel-border corners of the image at the far plane lie on the box's lateral faces
    for u, v in itertools.product((-0.5, INTR.width - 0.5), (-0.5, INTR.height - 0.5)):
        x, y = (u - INTR.cx) / INTR.focal * 1.8, (v - INTR.cy) / INTR.focal * 1.8
        assert min(abs(x - grid.lo[0]), abs(x - grid.hi[0])) < 1e-9
        assert min(abs(y - grid.lo[1]), abs(y - grid.hi[1])) < 1e-9
    with pytest.raises(DepthnerfError):
        CameraGrid.from_frustum(C2W, INTR, 1.8, 0.8)


def test_frustum_box_of_a_wide_image_is_the_bounding_box_of_its_corner_rays():
    """A 40 x 16 (W x H) image with an off-centre principal point: the box is the min / max over the 8 points
    where the rays through the image's pixel-border corners meet z_near and z_far."""
    intr = Intrinsics(focal=50.0, cx=20.5, cy=9.0, height=16, width=40)
    corners = np.array([[(u - intr.cx) / intr.focal * z, (v - intr.cy) / intr.focal * z, z]
                        for u in (-0.5, 39.5) for v in (-0.5, 15.5) for z in (0.8, 1.8)])
    grid = CameraGrid.from_frustum(C2W, intr, 0.8, 1.8)
    np.testing.assert_allclose(grid.lo, corners.min(0), rtol=0, atol=1e-12)
    np.testing.assert_allclose(grid.hi, corners.max(0), rtol=0, atol=1e-12)


def test_density_samples_are_at_the_world_positions_of_the_grid():
    grid = CameraGrid.from_frustum(C2W, INTR, 0.8, 1.8)
    config = MeshConfig(resolution=5, chunk=7)  # chunk does not divide the grid size
    vol = sample_density(lambda p: p[:, 0] + 10 * p[:, 1] + 100 * p[:, 2], grid, config)
    rot, trans = C2W[:3, :3].double().numpy(), C2W[:3, 3].double().numpy()
    for i, j, k in itertools.product(*(range(n) for n in vol.values.shape)):  # brute force, one sample at a time
        world = rot @ (vol.origin + np.array([i, j, k]) * vol.step) + trans
        assert vol.values[i, j, k] == pytest.approx(world @ [1, 10, 100], abs=1e-4)
    big = sample_density(lambda p: p[:, 0] + 10 * p[:, 1] + 100 * p[:, 2], grid, MeshConfig(resolution=5))
    # another chunking may change float32 rounding (e.g. other matmul shapes on CUDA): |values| <= ~300 here,
    # so a few float32 ulps are ~1e-5
    np.testing.assert_allclose(vol.values, big.values, rtol=1e-6, atol=1e-4)


def test_marching_cubes_recovers_a_sphere_in_world_coordinates():
    radius = 0.4
    grid = CameraGrid.from_frustum(C2W, INTR, 0.8, 2.0)
    mesh = extract_mesh(sphere_density(radius), grid, MeshConfig(resolution=64))
    dist = np.linalg.norm(mesh.vertices - CENTRE.numpy(), axis=1)
    assert np.abs(dist - radius).max() < 0.002  # voxel side is 0.032
    assert mesh.is_watertight and mesh.volume == pytest.approx(4 / 3 * math.pi * radius**3, rel=0.01)  # outward
    # the sphere is where the camera sees it: its centre projects near the image point of CENTRE
    uv = project(world_to_camera(torch.tensor(mesh.vertices.mean(0), dtype=torch.float32)[None], C2W),
                 INTR.focal, (INTR.cx, INTR.cy))
    uv_ref = project(world_to_camera(CENTRE[None], C2W), INTR.focal, (INTR.cx, INTR.cy))
    assert torch.allclose(uv, uv_ref, atol=0.2)
    surface = sample_surface(mesh, 20_000, seed=0)  # faces too, not only vertices, are on the sphere
    assert np.abs(np.linalg.norm(surface - CENTRE.numpy(), axis=1) - radius).mean() < 0.001
    gt = trimesh.creation.icosphere(subdivisions=5, radius=radius).apply_translation(CENTRE.numpy())
    # 20k samples on this area leave ~0.005 of sampling noise in Chamfer-L1 (see test_closed_forms...)
    assert chamfer_l1(mesh, gt, n_points=20_000, normalize=False) < 0.007


def test_box_boundary_is_capped_only_when_asked():
    grid = CameraGrid.world_box((-0.2, -0.2, -0.2), (0.2, 0.2, 0.2))  # entirely inside the sphere of 0.4
    density = sphere_density(0.4, centre=torch.zeros(3))
    capped = extract_mesh(density, grid, MeshConfig(resolution=24))
    step = grid.layout(24)[1]
    assert capped.is_watertight and 0.4**3 < capped.volume < (0.4 + 2 * step) ** 3  # the box, capped within a voxel
    assert np.all(np.abs(capped.bounds) < 0.2 + step)
    opened = extract_mesh(density, grid, MeshConfig(resolution=24, close_boundary=False))
    assert len(opened.faces) == 0  # no crossing inside the box without the padding
    cut = CameraGrid.world_box((-0.5, -0.5, 0.0), (0.5, 0.5, 0.5))  # half of the sphere
    half = extract_mesh(density, cut, MeshConfig(resolution=32))
    half_open = extract_mesh(density, cut, MeshConfig(resolution=32, close_boundary=False))
    half_volume, cap_step = 2 / 3 * math.pi * 0.4**3, cut.layout(32)[1]  # the cap lies within a voxel of z = 0
    assert half.is_watertight and half_volume < half.volume < half_volume + math.pi * 0.4**2 * 2 * cap_step
    assert not half_open.is_watertight


def test_empty_bad_and_coloured_extraction():
    grid = CameraGrid.world_box((-0.5,) * 3, (0.5,) * 3)
    empty = extract_mesh(lambda p: torch.zeros(len(p)), grid, MeshConfig(resolution=8))
    assert len(empty.vertices) == 0 and len(empty.faces) == 0
    with pytest.raises(DepthnerfError, match="non-finite"):
        extract_mesh(lambda p: torch.full((len(p),), float("nan")), grid, MeshConfig(resolution=8))
    with pytest.raises(DepthnerfError, match="returned shape"):
        extract_mesh(lambda p: torch.zeros(len(p), 2), grid, MeshConfig(resolution=8))
    mesh = extract_mesh(sphere_density(0.3, torch.zeros(3)), grid, MeshConfig(resolution=16),
                        color_fn=lambda p: (p + 0.5).clamp(0, 1))
    expected = np.round(np.clip(mesh.vertices + 0.5, 0, 1) * 255)
    np.testing.assert_allclose(mesh.visual.vertex_colors[:, :3], expected, atol=1)
    assert (mesh.visual.vertex_colors[:, 3] == 255).all()


def test_read_mesh_roundtrip_and_errors(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    sphere.export(tmp_path / "mesh.ply")
    loaded = read_mesh(tmp_path / "mesh.ply")
    np.testing.assert_allclose(loaded.vertices, sphere.vertices, atol=1e-6)
    with pytest.raises(DepthnerfError, match="not found"):
        read_mesh(tmp_path / "missing.ply")
    (tmp_path / "bad.ply").write_text("ply\nformat ascii 1.0\nelement vertex 1\nend_header\n")
    with pytest.raises(DepthnerfError, match="bad.ply"):
        read_mesh(tmp_path / "bad.ply")
    broken = sphere.copy()
    broken.vertices[3] = np.nan
    broken.export(tmp_path / "nan.ply")
    with pytest.raises(DepthnerfError, match="nan.ply: mesh has non-finite vertices"):
        read_mesh(tmp_path / "nan.ply")
    (tmp_path / "index.ply").write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                                        "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
                                        "end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 99\n")
    with pytest.raises(DepthnerfError, match=r"index.ply: face 0 names vertex 99, but the mesh has 3 vertices"):
        read_mesh(tmp_path / "index.ply")
    flat = sphere.copy()
    flat.vertices[:] = 0.0
    flat.export(tmp_path / "flat.ply")
    with pytest.raises(DepthnerfError, match="flat.ply: mesh has no surface"):
        read_mesh(tmp_path / "flat.ply")


def test_a_level_at_or_below_zero_is_capped_by_empty_space_below_it():
    """The level set ``-|p| = -0.3`` (a sphere of radius 0.3, inside where the field exceeds the level) in the box
    [-0.5, 0.5]^3: the padding must lie below the level, as the field outside the sphere does, so the mesh is the
    sphere alone, not also a shell at the box's border."""
    grid = CameraGrid.world_box((-0.5,) * 3, (0.5,) * 3)
    mesh = extract_mesh(lambda p: -p.norm(dim=-1), grid, MeshConfig(resolution=24, threshold=-0.3))
    step = grid.layout(24)[1]
    radii = np.linalg.norm(mesh.vertices, axis=1)
    assert mesh.is_watertight and np.abs(radii - 0.3).max() < step / 2
    assert 4 / 3 * math.pi * (0.3 - step / 2) ** 3 < mesh.volume < 4 / 3 * math.pi * 0.3**3


def test_a_density_that_only_reaches_the_level_gives_an_empty_mesh():
    """Nothing exceeds the level (a plateau exactly at it): no surface, an empty mesh and no error, with or without
    the padding."""
    grid = CameraGrid.world_box((-0.5,) * 3, (0.5,) * 3)
    for close in (True, False):
        config = MeshConfig(resolution=8, threshold=20.0, close_boundary=close)
        mesh = extract_mesh(lambda p: torch.full((len(p),), 20.0), grid, config)
        assert len(mesh.vertices) == 0 and len(mesh.faces) == 0


def test_vertex_colours_are_the_nearest_8_bit_values():
    """RGB (0.45, 0.05, 1.2) is clipped to [0, 1] and rounded to the nearest 8-bit value: 114.75 -> 115,
    12.75 -> 13, 1 -> 255; alpha 255."""
    grid = CameraGrid.world_box((-0.5,) * 3, (0.5,) * 3)
    colour = torch.tensor([0.45, 0.05, 1.2])
    mesh = extract_mesh(sphere_density(0.3, torch.zeros(3)), grid, MeshConfig(resolution=8),
                        color_fn=lambda p: colour.expand(len(p), 3))
    assert len(mesh.vertices) > 0
    assert mesh.visual.vertex_colors.tolist() == [[115, 13, 255, 255]] * len(mesh.vertices)


def _pieces_by_union_find(faces: np.ndarray) -> list[set[int]]:
    """Brute force: faces are joined when they share an edge (an unordered vertex pair)."""
    parent = list(range(len(faces)))

    def root(i: int) -> int:
        while parent[i] != i:
            i = parent[i]
        return i

    edges = [{frozenset(e) for e in itertools.combinations(f.tolist(), 2)} for f in faces]
    for a, b in itertools.combinations(range(len(faces)), 2):
        if edges[a] & edges[b]:
            parent[root(a)] = root(b)
    groups: dict[int, set[int]] = {}
    for i in range(len(faces)):
        groups.setdefault(root(i), set()).add(i)
    return list(groups.values())


def test_keep_largest_piece_matches_a_brute_force_union_find():
    parts = [trimesh.creation.icosphere(subdivisions=1, radius=0.3).apply_translation((x, 0, 0))
             for x in (-1.0, 1.0)] + [trimesh.creation.box((0.2, 0.2, 0.2)).apply_translation((0, 1, 0))]
    parts.append(trimesh.creation.icosphere(subdivisions=2, radius=0.2))  # the largest: 320 faces
    mesh = trimesh.util.concatenate(parts)
    # two triangles meeting at a single vertex are two pieces, not one
    corner = len(mesh.vertices)
    bowtie = [[corner, corner + 1, corner + 2], [corner, corner + 3, corner + 4]]
    mesh = trimesh.Trimesh(np.vstack([mesh.vertices, [[2, 2, 2], [3, 2, 2], [2, 3, 2], [1, 2, 2], [2, 1, 2]]]),
                           np.vstack([mesh.faces, bowtie]), process=False)
    mesh.visual.vertex_colors = np.column_stack([np.arange(len(mesh.vertices)) % 256] * 3 + [
        np.full(len(mesh.vertices), 255)]).astype(np.uint8)
    truth = _pieces_by_union_find(np.asarray(mesh.faces))
    biggest = max(truth, key=len)
    kept, pieces = keep_pieces(mesh, "largest")
    counts = (pieces.pieces, pieces.faces, pieces.kept_faces)
    assert counts == (len(truth), len(mesh.faces), len(biggest)) == (6, 494, 320)
    want = {tuple(sorted(map(tuple, mesh.vertices[f].round(6).tolist()))) for f in mesh.faces[sorted(biggest)]}
    got = {tuple(sorted(map(tuple, kept.vertices[f].round(6).tolist()))) for f in kept.faces}
    assert got == want and len(kept.vertices) == 162  # the subdivided sphere's vertices, no stray ones
    original = {tuple(v): tuple(c) for v, c in zip(mesh.vertices.round(6).tolist(),
                                                    mesh.visual.vertex_colors.tolist(), strict=True)}
    assert all(original[tuple(v)] == tuple(c) for v, c in zip(kept.vertices.round(6).tolist(),
                                                               kept.visual.vertex_colors.tolist(), strict=True))
    whole, counted = keep_pieces(mesh, "all")
    assert whole is mesh and (counted.pieces, counted.kept_faces) == (6, 494)
    assert keep_pieces(trimesh.Trimesh(), "largest")[1].pieces == 0
    with pytest.raises(DepthnerfError, match="--mesh-keep must be one of all, largest"):
        keep_pieces(mesh, "biggest")


def test_nearest_distances_match_brute_force():
    rng = np.random.default_rng(0)
    src, dst = rng.normal(size=(20, 3)), rng.normal(size=(30, 3))
    brute = np.array([min(np.linalg.norm(s - d) for d in dst) for s in src])
    np.testing.assert_allclose(nearest_distances(src, dst), brute, rtol=1e-12)


def test_chamfer_is_the_mean_of_the_two_directed_means():
    a = trimesh.creation.box(extents=(1.0, 0.5, 0.3))
    b = trimesh.creation.icosphere(subdivisions=2, radius=0.4).apply_translation((0.1, 0, 0))
    pa, pb = sample_surface(a, 500, 3), sample_surface(b, 500, 3)
    to_b = np.array([np.linalg.norm(pb - p, axis=1).min() for p in pa])
    to_a = np.array([np.linalg.norm(pa - p, axis=1).min() for p in pb])
    m = geometry_metrics(a, b, GeometryConfig(n_points=500, seed=3, tau=0.05, normalize=False))
    assert m.accuracy == pytest.approx(to_b.mean()) and m.completeness == pytest.approx(to_a.mean())
    assert m.chamfer_l1 == pytest.approx((to_a.mean() + to_b.mean()) / 2)
    assert (m.precision, m.recall) == pytest.approx(((to_b < 0.05).mean(), (to_a < 0.05).mean()))


def test_closed_forms_identical_and_offset_spheres():
    r, d = 0.5, 0.05
    inner = trimesh.creation.icosphere(subdivisions=5, radius=r)
    outer = trimesh.creation.icosphere(subdivisions=5, radius=r + d)
    assert chamfer_l1(inner, inner, n_points=5000) == 0.0 and fscore(inner, inner, n_points=5000) == 1.0
    assert chamfer_l1(outer, inner, n_points=20_000, normalize=False) == pytest.approx(d, rel=0.03)
    assert fscore(outer, inner, tau=0.8 * d, n_points=20_000, normalize=False) == 0.0
    assert fscore(outer, inner, tau=1.2 * d, n_points=20_000, normalize=False) == 1.0


def test_fscore_of_half_the_object_is_two_thirds():
    a = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    b = a.copy().apply_translation((2.0, 0, 0))
    gt = trimesh.util.concatenate([a, b])  # prediction finds one of two equal parts: P = 1, R = 1/2
    m = geometry_metrics(a, gt, GeometryConfig(n_points=20_000, tau=0.01))
    assert m.precision == 1.0 and m.recall == pytest.approx(0.5, abs=0.02)
    assert m.fscore == pytest.approx(2 / 3, abs=0.015)


def test_normalisation_by_gt_diagonal_and_determinism():
    r, d = 0.5, 0.05
    inner = trimesh.creation.icosphere(subdivisions=4, radius=r)
    outer = trimesh.creation.icosphere(subdivisions=4, radius=r + d)
    base = geometry_metrics(outer, inner, GeometryConfig(n_points=5000))
    diag = float(np.linalg.norm(inner.bounds[1] - inner.bounds[0]))  # of the GT mesh, not the prediction
    assert base.scale == pytest.approx(diag) and diag == pytest.approx(2 * r * math.sqrt(3), rel=0.02)
    raw = geometry_metrics(outer, inner, GeometryConfig(n_points=5000, normalize=False))
    assert base.chamfer_l1 == pytest.approx(raw.chamfer_l1 / diag)
    scaled = geometry_metrics(outer.copy().apply_scale(3.0), inner.copy().apply_scale(3.0),
                              GeometryConfig(n_points=5000))
    assert scaled.chamfer_l1 == pytest.approx(base.chamfer_l1) and scaled.fscore == base.fscore
    assert geometry_metrics(outer, inner, GeometryConfig(n_points=5000)) == base  # same seed, same numbers
    assert geometry_metrics(outer, inner, GeometryConfig(n_points=5000, seed=1)).chamfer_l1 != base.chamfer_l1


def test_empty_prediction_gets_worst_case_values():
    gt = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    m = geometry_metrics(trimesh.Trimesh(), gt)
    assert m.empty_prediction and (m.chamfer_l1, m.fscore, m.precision, m.recall) == (1.0, 0.0, 0.0, 0.0)
    raw = geometry_metrics(trimesh.Trimesh(), gt, GeometryConfig(normalize=False))
    assert raw.chamfer_l1 == pytest.approx(np.linalg.norm(gt.bounds[1] - gt.bounds[0]))
    with pytest.raises(DepthnerfError, match="ground-truth mesh has no surface"):
        geometry_metrics(gt, trimesh.Trimesh())
    ok = geometry_metrics(gt, gt, GeometryConfig(n_points=1000))
    summary = summarize_geometry([m, ok])
    assert summary["chamfer_l1"] == pytest.approx(0.5) and summary["fscore"] == pytest.approx(0.5)
    assert summary["empty_predictions"] == 1 and summary["fscore_tau"] == 0.01
