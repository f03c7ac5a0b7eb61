"""Orbit cameras and the point cloud of rendered views (:mod:`depthnerf.reconstruct.orbit`) against closed forms:
the orbit circle and its bounds, the SRN intrinsics formula of the module docstring, and the kept / subsampled
points counted by a loop over the pixels."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from depthnerf.data.cameras import Intrinsics
from depthnerf.errors import DepthnerfError
from depthnerf.reconstruct.orbit import orbit_points, orbit_poses, srn_intrinsics
from depthnerf.render.views import ViewRenders


@pytest.mark.parametrize("elevation", [-89.0, 0.0, 30.0, 89.0])
def test_orbit_cameras_sit_on_the_documented_circle_at_the_elevation_bounds(elevation):
    """Eye ``k`` of N at ``r (cos e cos a_k, cos e sin a_k, sin e)`` with ``a_k = a0 + 360 k / N``, looking at the
    origin (camera +z = -eye / r); the bounds -89 and 89 degrees are inside the accepted range."""
    radius, views, start = 2.5, 5, 20.0
    poses = orbit_poses(radius, elevation, views, start)
    e = math.radians(elevation)
    for k in range(views):
        a = math.radians(start + 360.0 * k / views)
        eye = radius * np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
        assert np.allclose(poses[k, :3, 3].numpy(), eye, atol=1e-5)
        assert np.allclose(poses[k, :3, 2].numpy(), -eye / radius, atol=1e-5)


@pytest.mark.parametrize("radius, elevation, views", [(1.0, 0.0, 0), (0.0, 0.0, 4), (-1.0, 0.0, 4),
                                                      (1.0, 89.5, 4), (1.0, -89.5, 4)])
def test_orbit_settings_outside_the_documented_ranges_are_refused(radius, elevation, views):
    """Ground truth: the documented ranges (views >= 1, radius > 0, elevation within [-89, 89])."""
    with pytest.raises(DepthnerfError):
        orbit_poses(radius, elevation, views)


@pytest.mark.parametrize("pixel_center", [0.0, 0.5])
@pytest.mark.parametrize("resolution", [64, 128, 200])
def test_srn_intrinsics_follow_the_module_docstring_formula(resolution, pixel_center):
    """Focal ``f r / S``; principal point ``(S/2 - c + 0.5) r / S - 0.5``: the SRN principal point ``S/2`` moved by
    the pixel centre ``c`` at the release size, then rescaled about pixel corners."""
    focal, size = 131.25, 128
    intr = srn_intrinsics(focal, size, resolution, pixel_center)
    scale = resolution / size
    centre = (size / 2 - pixel_center + 0.5) * scale - 0.5
    assert (intr.height, intr.width) == (resolution, resolution)
    assert intr.focal == pytest.approx(focal * scale) and intr.cx == pytest.approx(centre)
    assert intr.cy == pytest.approx(centre)


@pytest.mark.parametrize("focal, resolution", [(0.0, 64), (-1.0, 64), (100.0, 0)])
def test_srn_intrinsics_refuse_a_non_positive_focal_or_resolution(focal, resolution):
    """Ground truth: the documented requirement focal > 0 and resolution >= 1."""
    with pytest.raises(DepthnerfError):
        srn_intrinsics(focal, 128, resolution)


def _one_view(opacity: list[float]) -> tuple[ViewRenders, torch.Tensor, Intrinsics]:
    """A 1 x W view looking down -z from (0, 0, 5), pixel j at distance ``1 + j`` with colour ``j / 10``."""
    w = len(opacity)
    pose = orbit_poses(5.0, 89.0, 1)
    rgb = torch.tensor([[[j / 10, 0.0, 0.0] for j in range(w)]])[None]
    distance = torch.tensor([[1.0 + j for j in range(w)]])[None]
    renders = ViewRenders(rgb=rgb, distance=distance, opacity=torch.tensor([[opacity]]))
    return renders, pose, Intrinsics(focal=3.0, cx=(w - 1) / 2, cy=0.0, height=1, width=w)


def test_orbit_points_keep_opacity_above_the_threshold_at_their_ray_distance():
    """A loop over the pixels: a pixel is kept when its opacity is strictly above ``min_opacity`` (one equal to it
    is not), its point lies at its rendered distance from the camera and keeps its colour."""
    opacity = [0.9, 0.5, 0.2, 0.7, 0.5000001]
    renders, pose, intr = _one_view(opacity)
    points, colors = orbit_points(renders, pose, intr, min_opacity=0.5, max_points=None)
    kept = [j for j, o in enumerate(opacity) if o > 0.5]
    assert kept == [0, 3, 4] and len(points) == len(kept)
    eye = pose[0, :3, 3].numpy()
    assert np.allclose(np.linalg.norm(points - eye, axis=1), [1.0 + j for j in kept], atol=1e-5)
    assert np.allclose(colors[:, 0], [j / 10 for j in kept])


def test_orbit_points_subsample_evenly_from_first_to_last():
    """Nine kept points subsampled to five: every second one (0, 2, 4, 6, 8), the first and the last included, in
    order, each with its own colour."""
    renders, pose, intr = _one_view([1.0] * 9)
    points, colors = orbit_points(renders, pose, intr, min_opacity=0.0, max_points=5)
    eye = pose[0, :3, 3].numpy()
    assert np.allclose(np.linalg.norm(points - eye, axis=1), [1.0, 3.0, 5.0, 7.0, 9.0], atol=1e-5)
    assert np.allclose(colors[:, 0], [0.0, 0.2, 0.4, 0.6, 0.8])
