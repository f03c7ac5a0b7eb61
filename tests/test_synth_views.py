"""Camera placements of the synthetic SRN protocol: rigid look-at poses, hemisphere and spiral geometry."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from depthnerf.data.cameras import Intrinsics, camera_rays
from depthnerf.data.synth.framing import SRN_INTRINSICS
from depthnerf.data.synth.generate import category_spec, object_poses, object_rngs
from depthnerf.data.synth.raycast import PixelRays
from depthnerf.data.synth.views import ViewConfig, hemisphere_eyes, poses_from_eyes, spiral_eyes


def _check_rigid_look_at(poses: np.ndarray, radius: float) -> None:
    rot, t = poses[:, :3, :3].astype(np.float64), poses[:, :3, 3].astype(np.float64)
    eye = np.broadcast_to(np.eye(3), rot.shape)
    np.testing.assert_allclose(np.swapaxes(rot, 1, 2) @ rot, eye, atol=1e-5)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-5)
    np.testing.assert_allclose(poses[:, 3], np.tile([0, 0, 0, 1], (len(poses), 1)), atol=0)
    np.testing.assert_allclose(np.linalg.norm(t, axis=1), radius, rtol=1e-6)
    # camera +z (forward) points at the origin; image up (-y) has a non-negative world-z component
    np.testing.assert_allclose(rot[:, :, 2], -t / radius, atol=1e-5)
    assert (-rot[:, 2, 1] >= -1e-6).all()
    # the origin projects to the principal point
    cam = np.einsum("nji,nj->ni", rot, -t)
    np.testing.assert_allclose(cam[:, :2] / cam[:, 2:], 0.0, atol=1e-5)


@pytest.mark.parametrize("category", ["cars", "chairs"])
def test_train_and_test_poses_are_rigid_look_at(category: str) -> None:
    spec = category_spec(category)
    for split, n in (("train", 50), ("test", 251)):
        poses = object_poses(split, n, spec, object_rngs(0, category, split, 3)[1])
        assert poses.shape == (n, 4, 4)
        _check_rigid_look_at(poses, spec.radius)


def test_hemisphere_is_upper_and_area_uniform() -> None:
    cfg = ViewConfig(radius=1.3)
    eyes = hemisphere_eyes(40000, cfg, np.random.default_rng(0))
    np.testing.assert_allclose(np.linalg.norm(eyes, axis=1), 1.3, rtol=1e-12)
    u = eyes[:, 2] / 1.3
    assert u.min() >= 0.0 and u.max() <= np.sin(np.radians(cfg.max_elevation_deg))
    # area-uniform <=> z uniform: 10 equal z-bins each hold ~10%; azimuth uniform too
    for values, lo, hi in ((u, 0.0, 1.0), (np.arctan2(eyes[:, 1], eyes[:, 0]), -np.pi, np.pi)):
        hist, _ = np.histogram(values, bins=10, range=(lo, hi))
        np.testing.assert_allclose(hist / len(values), 0.1, atol=0.01)
    # a naive elevation-uniform sampler would fail the same check (the test can fail)
    elev = np.random.default_rng(1).uniform(0, np.pi / 2, 40000)
    hist, _ = np.histogram(np.sin(elev), bins=10, range=(0, 1))
    assert np.abs(hist / 40000 - 0.1).max() > 0.01


def test_spiral_geometry_and_input_view() -> None:
    cfg = ViewConfig(radius=2.0)
    eyes = spiral_eyes(251, cfg)
    assert eyes.shape == (251, 3)
    np.testing.assert_allclose(np.linalg.norm(eyes, axis=1), 2.0, rtol=1e-12)
    elev = np.degrees(np.arcsin(eyes[:, 2] / 2.0))
    assert elev[0] == pytest.approx(0.0, abs=1e-9) and elev[-1] == pytest.approx(cfg.max_elevation_deg)
    assert (np.diff(elev) > 0).all()  # strictly monotone
    azim = np.unwrap(np.arctan2(eyes[:, 1], eyes[:, 0]))
    steps = np.diff(azim)
    np.testing.assert_allclose(steps, cfg.spiral_azimuth_span / 250, rtol=1e-6)  # Archimedean: constant rate
    # view 64: side-ish, low elevation, at the configured azimuth from the object's front
    assert 15.0 < elev[64] < 30.0
    assert np.degrees(np.arctan2(eyes[64, 1], eyes[64, 0])) == pytest.approx(cfg.input_azimuth_deg)


def test_poses_from_eyes_match_look_at_roll() -> None:
    eyes = np.array([[1.3, 0.0, 0.0], [0.0, -1.3, 0.5], [0.1, 0.1, 1.29]])
    poses = poses_from_eyes(eyes)
    for p, e in zip(poses, eyes, strict=True):
        np.testing.assert_allclose(p[:3, 3], e, atol=1e-6)
        np.testing.assert_allclose(p[:3, 2], -e / np.linalg.norm(e), atol=1e-6)
        assert abs(p[2, 0]) < 1e-6  # camera x (image right) is horizontal: no roll


def test_pixel_rays_equal_camera_rays() -> None:
    intr = SRN_INTRINSICS.resized(32, 32)
    pose = poses_from_eyes(spiral_eyes(251, ViewConfig(radius=1.3)))[64]
    origins, dirs = PixelRays.world(PixelRays(intr).centre, pose)
    ref_o, ref_d = camera_rays(torch.as_tensor(pose), intr)
    np.testing.assert_allclose(dirs, ref_d.reshape(-1, 3).numpy(), atol=2e-7)
    np.testing.assert_allclose(origins, ref_o.reshape(-1, 3).numpy(), atol=1e-7)
    # sub-sample rays are the centre rays shifted by the RGSS offsets (u + du, v + dv)
    sub = PixelRays(intr).subsamples[0]
    shifted = camera_rays(torch.eye(4), Intrinsics(intr.focal, intr.cx - 0.125, intr.cy - 0.375, 32, 32))[1]
    np.testing.assert_allclose(sub, shifted.reshape(-1, 3).numpy(), atol=2e-7)


def test_srn_intrinsics_scale_with_resolution() -> None:
    assert SRN_INTRINSICS.focal == 131.25 and (SRN_INTRINSICS.cx, SRN_INTRINSICS.cy) == (64.0, 64.0)
    small = SRN_INTRINSICS.resized(64, 64)
    assert small.focal == pytest.approx(65.625) and small.cx == pytest.approx(31.75)
