"""scripts/mesh_check.py: the release gate on reconstruct meshes, against hand-built scenes."""

from __future__ import annotations

import numpy as np
import trimesh
from fixtures_scripts import load_script


def _load():
    return load_script("mesh_check")


def _camera() -> tuple[np.ndarray, np.ndarray]:
    """A camera on -y looking at the origin (+z up; OpenCV axes: x right, y down, z forward)."""
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([(1.0, 0, 0), (0, 0, -1.0), (0, 1.0, 0)], axis=1)  # columns: cam x, y, z in world
    c2w[:3, 3] = [0.0, -3.0, 0.0]
    return c2w, np.array([32.0, 15.5, 15.5, 32, 32])


def _scene(with_slab: bool) -> trimesh.Trimesh:
    body = trimesh.creation.box(extents=(1.0, 1.0, 0.5))
    if not with_slab:
        return body
    slab = trimesh.creation.box(extents=(1.0, 1.0, 0.05),
                                transform=trimesh.transformations.translation_matrix((0.0, 0.0, 1.2)))
    return trimesh.util.concatenate([body, slab])


def test_projection_matches_a_pixel_loop() -> None:
    mc = _load()
    c2w, intr = _camera()
    mask = np.zeros((32, 32), dtype=bool)
    mask[10:22, 8:24] = True
    pts = np.random.default_rng(0).uniform(-1.5, 1.5, size=(200, 3))
    got = mc.inside_mask(pts, c2w, intr, mask)
    for p, g in zip(pts, got, strict=True):
        x, y, z = (p - c2w[:3, 3]) @ c2w[:3, :3]
        u, v = round(32.0 * x / z + 15.5), round(32.0 * y / z + 15.5)
        assert g == (z > 0 and 0 <= u < 32 and 0 <= v < 32 and bool(mask[v, u]))


def test_slab_above_the_object_fails_the_gate() -> None:
    mc = _load()
    c2w, intr = _camera()
    body = _scene(False)
    mask = mc.inside_mask(np.asarray(body.vertices) * 1.01, c2w, intr, np.ones((32, 32), bool))  # sanity
    assert mask.all()
    # the input mask: the body's silhouette (a box 1.0 wide, 0.5 tall at distance ~2.5-3.5)
    sil = np.zeros((32, 32), dtype=bool)
    sil[11:21, 6:26] = True
    clean = mc.mesh_report(body, c2w, intr, sil, 0.10)
    assert clean["components"] == 1 and clean["main_share"] == 1.0 and clean["above_share"] == 0.0
    dirty = mc.mesh_report(_scene(True), c2w, intr, sil, 0.10)
    assert dirty["components"] == 2 and dirty["main_share"] == 0.5  # 12 + 12 faces
    assert dirty["above_share"] == 0.5  # every slab face is 0.95 above the body's top (height 0.5)


def test_edge_distance_matches_a_pixel_loop() -> None:
    mc = _load()
    c2w, intr = _camera()
    mask = np.zeros((32, 32), dtype=bool)
    mask[10:22, 8:24] = True
    mask[3, 28] = True  # a lone pixel, so the nearest mask pixel is not always on the rectangle
    pts = np.random.default_rng(1).uniform(-2.0, 2.0, size=(150, 3))
    pts[0] = c2w[:3, 3] - (0.0, 1.0, 0.0)  # behind the camera
    got = mc.edge_distance_px(pts, c2w, intr, mask)
    assert np.isinf(got[0])
    for p, g in zip(pts[1:], got[1:], strict=True):
        x, y, z = (p - c2w[:3, 3]) @ c2w[:3, :3]
        if z <= 0:
            assert np.isinf(g)
            continue
        u, v = 32.0 * x / z + 15.5, 32.0 * y / z + 15.5
        want = min(np.hypot(u - j, v - i) for i in range(32) for j in range(32) if mask[i, j])
        assert abs(g - want) < 1e-9
    assert np.isinf(mc.edge_distance_px(pts, c2w, intr, np.zeros((32, 32), bool))).all()


def test_edge_report_tells_a_rim_from_a_slab() -> None:
    mc = _load()
    c2w, intr = _camera()
    sil = np.zeros((32, 32), dtype=bool)
    sil[14:18, 11:20] = True  # narrower than the body's face centroids (u 9.9-21.1, v 12.7-18.3), by <= 1.7 px
    rim = mc.mesh_report(_scene(False), c2w, intr, sil, 0.10)["outside_edge_px"]
    slab = mc.mesh_report(_scene(True), c2w, intr, sil, 0.10)["outside_edge_px"]
    assert rim["within_3px_share"] == 1.0 and rim["p95"] <= 3.0
    assert slab["p95"] > 5.0 and slab["within_3px_share"] < 1.0


def _box(extents: tuple[float, float, float], centre: tuple[float, float, float]) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=extents, transform=trimesh.transformations.translation_matrix(centre))


def _ray_hits_triangle(origin: np.ndarray, direction: np.ndarray, tri: np.ndarray) -> float:
    """Distance along a unit ray to a triangle, inf on a miss: the plane hit, then the same-side test per edge."""
    normal = np.cross(tri[1] - tri[0], tri[2] - tri[0])
    denom = normal @ direction
    if abs(denom) < 1e-12:
        return np.inf
    t = normal @ (tri[0] - origin) / denom
    if t <= 0:
        return np.inf
    hit = origin + t * direction
    signs = [np.cross(tri[(k + 1) % 3] - tri[k], hit - tri[k]) @ normal for k in range(3)]
    return t if min(signs) >= -1e-12 or max(signs) <= 1e-12 else np.inf


def test_visible_faces_match_a_ray_loop() -> None:
    mc = _load()
    c2w, _ = _camera()
    scene = trimesh.util.concatenate([_box((1.0, 1.0, 0.5), (0.0, 0.0, 0.0)), _box((0.3, 0.3, 0.3), (0.2, 1.5, 0.0)),
                                      _box((0.2, 0.2, 0.2), (0.9, -0.2, 0.1))])
    got = mc.visible_faces(scene, c2w[:3, 3])
    origin = c2w[:3, 3]
    for k, centre in enumerate(scene.triangles_center):
        dist = np.linalg.norm(centre - origin)
        direction = (centre - origin) / dist
        nearest = min(_ray_hits_triangle(origin, direction, tri) for tri in scene.triangles)
        assert got[k] == (nearest >= dist * (1.0 - 1e-4)), k
    assert 0 < got.sum() < len(got)  # the front faces only; the box behind the body is hidden whole
    assert not got[12:24].any() and got[24:36].any()  # boxes: body 0-11, behind it 12-23, beside it 24-35


def test_a_detached_part_the_photo_shows_counts_as_the_object() -> None:
    mc = _load()
    c2w, intr = _camera()
    body = _box((1.0, 1.0, 0.5), (0.0, 0.0, 0.0))
    runner = _box((0.6, 0.2, 0.05), (0.0, 0.0, -0.4))  # below the body, cut off from it: a chair's floor runner
    hidden = _box((0.3, 0.3, 0.3), (0.0, 1.5, 0.0))  # on the mask, behind the body: the camera never sees it
    beside = _box((0.2, 0.2, 0.2), (1.2, 0.0, 0.0))  # in view, off the mask
    sil = np.zeros((32, 32), dtype=bool)
    sil[11:23, 6:26] = True  # the body (rows 12-19) and the runner (rows 19-21)
    assert mc.inside_mask(runner.triangles_center, c2w, intr, sil).all()
    assert mc.inside_mask(hidden.triangles_center, c2w, intr, sil).all()
    assert not mc.inside_mask(beside.triangles_center, c2w, intr, sil).any()
    with_runner = mc.mesh_report(trimesh.util.concatenate([body, runner]), c2w, intr, sil, 0.10)
    assert with_runner["components"] == 2 and with_runner["main_share"] == 0.5  # 12 + 12 faces
    assert with_runner["seen_pieces"] == 1 and with_runner["object_share"] == 1.0
    for stray in (hidden, beside):
        rep = mc.mesh_report(trimesh.util.concatenate([body, stray]), c2w, intr, sil, 0.10)
        assert rep["seen_pieces"] == 0 and rep["object_share"] == rep["main_share"] == 0.5
    # a box shows at most 3 of its 6 sides: 0.5 of its faces, so --min-seen above that counts it stray
    strict = mc.mesh_report(trimesh.util.concatenate([body, runner]), c2w, intr, sil, 0.10, min_seen=0.6)
    assert strict["seen_pieces"] == 0 and strict["object_share"] == 0.5


def test_a_corrupt_file_of_a_folder_is_one_error_line(tmp_path, capsys) -> None:
    from PIL import Image

    mod = _load()
    folder = tmp_path / "out"
    folder.mkdir()
    trimesh.creation.box(extents=(0.4, 0.4, 0.4)).export(folder / "mesh.ply")
    c2w = np.eye(4)
    c2w[2, 3] = -2.0
    np.savez(folder / "depths.npz", poses=c2w[None], intrinsics=np.array([32.0, 15.5, 15.5, 32, 32]))
    Image.fromarray(np.full((32, 32), 255, np.uint8)).save(folder / "input_mask.png")
    assert mod.main([str(folder)]) in (0, 1)
    capsys.readouterr()
    for name, junk in (("depths.npz", b"not a zip"), ("input_mask.png", b"\x89PNG broken"), ("mesh.ply", b"ply\nx")):
        good = (folder / name).read_bytes()
        (folder / name).write_bytes(junk)
        assert mod.main([str(folder)]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"error: {folder / name}: unreadable") and err.count("\n") == 1, err
        (folder / name).write_bytes(good)
    np.savez(folder / "depths.npz", intrinsics=np.ones(5))  # no poses
    assert mod.main([str(folder)]) == 2
    assert "depths.npz: unreadable (KeyError" in capsys.readouterr().err
