"""Camera conventions of ``depthnerf.data.cameras`` against closed forms: resizing, projection, pose inversion."""

from __future__ import annotations

import pytest
import torch

from depthnerf.data.cameras import Intrinsics, invert_pose, look_at, project, world_to_camera


def test_resize_is_uniform_and_maps_pixel_edges_to_pixel_edges():
    """A resize by ``s`` maps ``f -> s f`` and ``c -> (c + 0.5) s - 0.5``, the same ``s`` on both axes; a resize
    that would stretch one axis is refused."""
    intr = Intrinsics(focal=60.0, cx=20.5, cy=9.5, height=24, width=48)
    half = intr.resized(12, 24)
    assert (half.focal, half.cx, half.cy, half.height, half.width) == (30.0, 10.0, 4.5, 12, 24)
    # the image's left/top border (-0.5) stays the border, the right/bottom one (W - 0.5) too
    for c, size, new_c, new_size in ((intr.cx, 48, half.cx, 24), (intr.cy, 24, half.cy, 12)):
        assert (-0.5 - c) * 0.5 == pytest.approx(-0.5 - new_c) and (size - 0.5 - c) * 0.5 == pytest.approx(
            new_size - 0.5 - new_c)
    for height, width in ((12, 48), (24, 24), (48, 48)):
        with pytest.raises(ValueError, match="non-uniform resize"):
            intr.resized(height, width)


def test_project_is_the_pinhole_formula_and_points_behind_the_camera_land_far_outside():
    pts = torch.tensor([[[0.2, -0.1, 2.0], [0.3, 0.1, -1.0], [0.05, -0.02, 0.0]]], dtype=torch.float64)
    uv = project(pts, 50.0, (16.0, 12.0))[0]
    assert torch.allclose(uv[0], torch.tensor([50 * 0.2 / 2 + 16, 50 * -0.1 / 2 + 12], dtype=torch.float64))
    # z <= 0: never inside a 32 x 24 image (a mirrored projection would be: (1, 7) for the second point)
    for k in (1, 2):
        assert torch.isfinite(uv[k]).all() and (uv[k] - torch.tensor([16.0, 12.0])).abs().min() > 1e5


def test_invert_pose_and_world_to_camera_are_the_rigid_inverse():
    c2w = look_at(torch.tensor([[1.1, -0.7, 0.6], [-0.3, 1.5, 0.9]])).double()
    c2w[:, :3, 3] += torch.tensor([0.2, -0.1, 0.3], dtype=torch.float64)  # look_at a point off the origin
    w2c = invert_pose(c2w)
    eye = torch.eye(4, dtype=torch.float64).expand(2, 4, 4)
    # look_at builds the rotation in float32: orthonormal to ~1e-7
    assert torch.allclose(w2c @ c2w, eye, atol=1e-6) and torch.allclose(c2w @ w2c, eye, atol=1e-6)
    pts = torch.randn(2, 5, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    homog = torch.cat([pts, torch.ones(2, 5, 1, dtype=torch.float64)], dim=-1)
    assert torch.allclose(world_to_camera(pts, c2w), (homog @ w2c.transpose(-1, -2))[..., :3], atol=1e-12)
