"""The auto marching-cubes level (half the median peak density over opaque input rays) and the visible-surface
ground truth (back-projected depth maps), both against closed forms."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from depthnerf.data import srn_format
from depthnerf.data.cameras import Intrinsics, camera_rays, look_at
from depthnerf.data.srn import ObjectRecord
from depthnerf.errors import DepthnerfError
from depthnerf.eval.geometry_metrics import (
    GeometryConfig,
    backproject_depth,
    object_geometry,
    summarize_geometry,
    visible_surface_points,
)
from depthnerf.render.mesh import MeshConfig, source_mesh
from depthnerf.render.mesh_level import DEFAULT_THRESHOLD, auto_level, levels_text, parse_level

INTR = Intrinsics(focal=24.0, cx=7.5, cy=7.5, height=16, width=16)
NEAR, FAR = 1.0, 3.0
RADIUS = 0.5


def _camera(azimuth: float = 0.3, elevation: float = 0.4) -> torch.Tensor:
    eye = 2.0 * torch.tensor([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                              np.sin(elevation)], dtype=torch.float32)
    return look_at(eye)


def ball(amplitude: float, softness: float = 0.0):
    """Density ``amplitude`` inside radius RADIUS; a logistic edge of width ``softness`` (0 = a hard step)."""
    def density(p: torch.Tensor) -> torch.Tensor:
        r = p.norm(dim=-1)
        if softness == 0:
            return torch.where(r < RADIUS, torch.tensor(amplitude), torch.tensor(0.0))
        return amplitude * torch.sigmoid((RADIUS - r) / softness)
    return density


def test_auto_level_is_half_the_density_of_a_constant_ball():
    level = auto_level(ball(7.0), _camera(), INTR, NEAR, FAR)
    assert level.rule == "auto" and level.level == pytest.approx(3.5, rel=1e-6)
    assert 0 < level.opaque_rays < level.rays == 8 * 8  # every 2nd row and column of 16x16; the ball covers part
    assert auto_level(ball(700.0), _camera(), INTR, NEAR, FAR).level == pytest.approx(350.0, rel=1e-6)  # scale-free


def test_soft_ball_auto_mesh_sits_at_the_half_maximum_radius():
    density, c2w = ball(5.0, softness=0.02), _camera()
    level = auto_level(density, c2w, INTR, NEAR, FAR)
    assert level.level == pytest.approx(2.5, rel=0.01)  # median peak = 5 sigmoid(>~10) ~ 5
    fixed, fixed_level = source_mesh(density, c2w, INTR, NEAR, FAR, MeshConfig(48, DEFAULT_THRESHOLD))
    assert len(fixed.faces) == 0 and fixed_level.rule == "fixed"  # soft field: the old fixed level finds nothing
    mesh, used = source_mesh(density, c2w, INTR, NEAR, FAR, MeshConfig(48, "auto"))
    assert used == level and len(mesh.faces) > 0
    radii = np.linalg.norm(mesh.vertices, axis=1)
    assert np.abs(radii - RADIUS).max() < 0.01  # sigmoid(0) = 1/2: the half-maximum surface is the sphere r = 0.5
    assert used.describe().startswith(
        f"auto level {level.level:.4g} = 0.5 x median peak density over {level.opaque_rays} of 64")
    assert f"median {level.level:.4g}" in levels_text([used], 48)


def test_auto_level_falls_back_without_opaque_rays():
    level = auto_level(lambda p: torch.full((len(p),), 0.1), _camera(), INTR, NEAR, FAR)  # opacity 1 - e^-0.2
    assert (level.level, level.rule, level.opaque_rays) == (DEFAULT_THRESHOLD, "fallback", 0)
    assert "fell back to density 20" in level.describe()
    assert "1 object(s) without an opaque ray" in levels_text([level], 32)


def test_ray_samples_are_bin_midpoints_and_negative_densities_add_no_opacity():
    """``input_ray_densities`` for a camera at the origin (unit ray directions, so a sample's distance from the
    eye is its ``t``): with ``sigma = |x|`` the peak is the last bin midpoint ``far - delta / 2`` and the opacity
    ``1 - exp(-delta sum_k t_k) = 1 - exp(-(far - near)(near + far) / 2)``; with ``sigma = +3`` left of the
    optical axis and ``-3`` right of it, the left rays have opacity ``1 - exp(-3 (far - near))`` and the right
    rays 0 (negative densities clipped)."""
    from depthnerf.render.mesh_level import input_ray_densities

    intr, near, far, samples = Intrinsics(focal=4.0, cx=1.5, cy=1.5, height=4, width=4), 1.0, 3.0, 8
    delta = (far - near) / samples
    queried = []

    def distance(p: torch.Tensor) -> torch.Tensor:
        queried.append(p.norm(dim=-1))
        return p.norm(dim=-1)

    peak, opacity = input_ray_densities(distance, torch.eye(4), intr, near, far, samples, chunk=5, ray_stride=1)
    t = torch.cat(queried).reshape(16, samples)
    torch.testing.assert_close(t, (near + (torch.arange(samples) + 0.5) * delta).expand(16, samples))
    np.testing.assert_allclose(peak, far - delta / 2, rtol=1e-6)
    np.testing.assert_allclose(opacity, 1 - np.exp(-(far - near) * (near + far) / 2), rtol=1e-6)
    peak, opacity = input_ray_densities(lambda p: torch.where(p[:, 0] < 0, 3.0, -3.0), torch.eye(4), intr, near,
                                        far, samples, ray_stride=1)
    left = np.arange(4) < 1.5  # pixel columns 0 and 1 lie left of cx = 1.5
    np.testing.assert_allclose(peak.reshape(4, 4), np.where(left, 3.0, -3.0)[None].repeat(4, 0))
    np.testing.assert_allclose(opacity.reshape(4, 4), np.where(left, 1 - np.exp(-3.0 * (far - near)), 0.0)[None]
                               .repeat(4, 0), rtol=1e-6, atol=1e-12)


def test_parse_level():
    assert parse_level("auto") == "auto" and parse_level(" AUTO ") == "auto" and parse_level("12.5") == 12.5
    assert parse_level("Silhouette") == "silhouette" and parse_level("local") == "local"
    for bad in ("twenty", "-1", "0", "nan"):
        with pytest.raises(DepthnerfError, match="--mesh-threshold"):
            parse_level(bad)
    with pytest.raises(DepthnerfError, match="mesh level must be a number or one of auto, silhouette, local"):
        source_mesh(ball(1.0), _camera(), INTR, NEAR, FAR, MeshConfig(8, "half"))


def sphere_depth(c2w: torch.Tensor, intr: Intrinsics, radius: float) -> np.ndarray:
    """Closed-form camera z-depth of a sphere at the origin (0 where the ray misses it)."""
    origins, dirs = camera_rays(c2w, intr)
    o, d = origins.double().numpy(), dirs.double().numpy()
    b = (o * d).sum(-1)
    disc = b**2 - ((o * o).sum(-1) - radius**2)
    t = -b - np.sqrt(np.clip(disc, 0, None))
    cos = d @ c2w[:3, 2].double().numpy()  # camera +z axis in the world: z = t cos(theta)
    return np.where(disc > 0, t * cos, 0.0).astype(np.float32)


def test_backprojected_depth_lies_on_the_sphere():
    c2w = _camera(1.1, 0.2)
    depth = sphere_depth(c2w, INTR, RADIUS)
    assert 0 < (depth > 0).sum() < depth.size
    points = backproject_depth(depth, c2w.numpy(), INTR)
    assert len(points) == (depth > 0).sum()
    assert np.abs(np.linalg.norm(points, axis=1) - RADIUS).max() < 1e-5
    assert (points @ c2w[:3, 3].double().numpy() > 0).all()  # only the side facing the camera


def _sphere_object(root: Path, views: int, intr: Intrinsics, pixel_center: float = 0.0) -> ObjectRecord:
    """A sphere object whose depth maps put pixel (i, j) at ``(j + pixel_center, i + pixel_center)`` in ``intr``."""
    srn_format.write_intrinsics(root / "intrinsics.txt", intr)
    for k in range(views):
        c2w = _camera(2 * np.pi * k / views, 0.3)
        srn_format.write_pose(root / "pose" / f"{k:06d}.txt", c2w.numpy())
        depth = sphere_depth(c2w, intr.with_pixel_center(pixel_center), RADIUS)
        srn_format.write_depth(root / "depth" / f"{k:06d}.npz", depth)
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=RADIUS)
    inner = trimesh.creation.icosphere(subdivisions=2, radius=RADIUS / 2)  # an interior part no view sees
    trimesh.util.concatenate([mesh, inner]).export(root / "mesh.ply")
    return ObjectRecord(category="cars", split="test", object_id="sphere", path=root,
                        view_names=tuple(f"{k:06d}" for k in range(views)), intrinsics=intr, has_depth=True,
                        has_mask=False, mesh_path=root / "mesh.ply")


def test_visible_surface_ground_truth(tmp_path):
    (tmp_path / "pose").mkdir()
    (tmp_path / "depth").mkdir()
    record = _sphere_object(tmp_path, 4, Intrinsics(focal=96.0, cx=31.5, cy=31.5, height=64, width=64))
    points = visible_surface_points(record, n_points=300)
    assert points.shape == (300, 3) and np.abs(np.linalg.norm(points, axis=1) - RADIUS).max() < 1e-5
    pred = trimesh.creation.icosphere(subdivisions=4, radius=RADIUS)  # = the outer (visible) surface
    cfg = GeometryConfig(n_points=20_000, tau=0.01)
    m = object_geometry(pred, record, cfg)
    assert m.ground_truth == "visible surface from 4 depth maps"
    assert m.completeness < 0.004 and m.recall > 0.99  # every visible GT point is on the prediction
    mesh_only = object_geometry(pred, ObjectRecord(**{**record.__dict__, "has_depth": False}), cfg)
    assert mesh_only.ground_truth == "mesh.ply"
    # the interior sphere (1/5 of the GT area, 0.25 / sqrt(3) diagonals inside) is counted as missed
    assert mesh_only.completeness > 0.02 and mesh_only.recall < 0.85
    assert summarize_geometry([m, m], cfg)["geometry_gt"] == "visible surface from 4 depth maps"
    assert summarize_geometry([m, mesh_only], cfg)["geometry_gt"] == (
        "mesh.ply (1 objects); visible surface from 4 depth maps (1 objects)")


def test_visible_surface_follows_the_depth_maps_pixel_centre(tmp_path):
    """Depth maps rendered at pixel centres ``(j + 0.5, i + 0.5)``: read with that convention every point is on the
    sphere; read half a pixel off, the points leave it."""
    (tmp_path / "pose").mkdir()
    (tmp_path / "depth").mkdir()
    record = _sphere_object(tmp_path, 2, Intrinsics(focal=48.0, cx=16.0, cy=16.0, height=32, width=32), 0.5)
    on = visible_surface_points(record, n_points=10_000, pixel_center=0.5)
    assert np.abs(np.linalg.norm(on, axis=1) - RADIUS).max() < 1e-5
    off = visible_surface_points(record, n_points=10_000, pixel_center=0.0)
    assert np.abs(np.linalg.norm(off, axis=1) - RADIUS).max() > 1e-3


def test_visible_surface_subsample_is_spread_evenly_over_every_view(tmp_path):
    """Fewer GT samples than object pixels: the kept points are every ``P / n``-th of all views' points in view
    order, so each view keeps its share ``n * P_view / P`` (up to rounding), not the first views all of it."""
    (tmp_path / "pose").mkdir()
    (tmp_path / "depth").mkdir()
    record = _sphere_object(tmp_path, 4, Intrinsics(focal=96.0, cx=31.5, cy=31.5, height=64, width=64))
    per_view = [backproject_depth(srn_format.read_depth(record.depth_path(k), record.depth_scale),
                                  srn_format.read_pose(record.pose_path(k)), record.intrinsics) for k in range(4)]
    total, n = sum(len(p) for p in per_view), 300
    assert all(len(p) > n for p in per_view)
    view_of = {tuple(p): k for k, pts in enumerate(per_view) for p in pts.round(9).tolist()}
    points = visible_surface_points(record, n_points=n)
    views = [view_of[tuple(p)] for p in points.round(9).tolist()]
    assert views == sorted(views)  # in view order
    for k, pts in enumerate(per_view):
        assert abs(views.count(k) - n * len(pts) / total) <= 1.5
    assert np.array_equal(points[0], per_view[0][0]) and np.array_equal(points[-1], per_view[-1][-1])
    assert visible_surface_points(record, n_points=total).shape == (total, 3)  # all of them: nothing dropped
