"""Vertex colour rules (depthnerf.render.mesh_colors) against brute-force compositing loops and closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from depthnerf.errors import DepthnerfError
from depthnerf.reconstruct.reconstructor import ReconstructConfig
from depthnerf.render import mesh_colors
from depthnerf.render.mesh_colors import MIN_OPACITY, NORMAL_RAY, POINT, normal_ray_colors, point_colors
from depthnerf.render.photo_colors import PHOTO


def smooth_field(points: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Density and colour that vary along every axis and with the viewing direction."""
    sigma = 4.0 + 3.0 * torch.sin(3 * points[..., 0]) + 2.0 * points[..., 1] ** 2 + 5.0 * points[..., 2].clamp(0)
    rgb = torch.sigmoid(torch.stack([points[..., 0] * 2, points[..., 1] - points[..., 2], points.sum(-1)], -1)
                        + 0.3 * dirs[:, None, :])
    return rgb, sigma


def brute_force_color(v: np.ndarray, n: np.ndarray, half: float, samples: int) -> np.ndarray:
    """The normal ray's colour, one sample at a time: T starts at 1, each sample adds alpha T c and keeps
    T (1 - alpha), alpha = 1 - exp(-sigma delta) with delta = 2 half / (samples - 1) for every sample."""
    delta = 2 * half / (samples - 1)
    total, acc, trans = np.zeros(3), 0.0, 1.0
    for k in range(samples):
        x = v + (half - k * delta) * n
        rgb, sigma = smooth_field(torch.tensor(x[None, None], dtype=torch.float64),
                                  torch.tensor(-n[None], dtype=torch.float64))
        alpha = 1 - math.exp(-max(float(sigma), 0.0) * delta)
        total += alpha * trans * rgb[0, 0].numpy()
        acc += alpha * trans
        trans *= 1 - alpha
    return total / acc


def unit_rows(rows: np.ndarray) -> np.ndarray:
    return rows / np.linalg.norm(rows, axis=1, keepdims=True)


def test_normal_ray_colour_is_the_brute_force_composite():
    rng = np.random.default_rng(0)
    v, n = rng.uniform(-0.5, 0.5, (7, 3)), unit_rows(rng.normal(size=(7, 3)))
    got = normal_ray_colors(smooth_field, torch.tensor(v, dtype=torch.float64), torch.tensor(n, dtype=torch.float64),
                            half_width=0.08, samples=9, chunk=18)  # 2 rays per chunk: chunking is covered
    expected = np.stack([brute_force_color(v[i], n[i], 0.08, 9) for i in range(7)])
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-5)  # float32 output


def test_a_hard_surface_gives_the_colour_just_inside_it_and_empty_space_the_point_colour():
    centre, radius = torch.tensor([0.1, -0.2, 0.3]), 0.25

    def ball(points: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        inside = (points - centre).norm(dim=-1) < radius
        rgb = torch.where(inside[..., None], torch.tensor([0.9, 0.1, 0.2]), torch.tensor([0.0, 0.0, 1.0]))
        rgb = torch.where(inside[..., None], rgb, (1 - dirs[:, None, :]) / 2)  # outside: shows the direction
        return rgb, torch.where(inside, 1e4, 0.0)

    n = torch.tensor(unit_rows(np.random.default_rng(1).normal(size=(20, 3))), dtype=torch.float32)
    on_sphere = centre + (radius - 1e-3) * n  # just inside, as marching cubes puts a vertex within a voxel
    got = normal_ray_colors(ball, on_sphere, n, half_width=0.05, samples=24, chunk=1000)
    np.testing.assert_allclose(got, np.tile([0.9, 0.1, 0.2], (20, 1)), atol=1e-6)  # opaque at its first sample in
    far = centre + 3 * radius * n  # no density within 0.05: the point colour, seen along -n
    got = normal_ray_colors(ball, far, n, half_width=0.05, samples=24, chunk=1000)
    np.testing.assert_allclose(got, (1 + n.numpy()) / 2, atol=1e-6)


def test_the_opacity_floor_switches_to_the_point_colour():
    def faint(points: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        red = 100 * (points[..., 0] - 0.5) ** 2  # 0 at the vertex, its mean over the ray's samples above 0
        return torch.stack([red, torch.full_like(red, 0.5), torch.zeros_like(red)], -1), torch.full_like(red, density)

    v, n, half, samples = torch.tensor([[0.5, 0.0, 0.0]]), torch.tensor([[1.0, 0.0, 0.0]]), 0.05, 24
    ray = 2 * half * samples / (samples - 1)  # every sample's interval counts, the last one's too
    # mean of x^2 over linspace(-h, h, S): h^2 (S + 1) / (3 (S - 1)); the weights of so faint a density are equal
    # to within 0.001%
    ray_mean = 100 * half**2 * (samples + 1) / (3 * (samples - 1))
    density = -math.log(1 - 2 * MIN_OPACITY) / ray  # opacity 2x the floor: the ray's colour
    np.testing.assert_allclose(normal_ray_colors(faint, v, n, half, samples, 100)[0], [ray_mean, 0.5, 0.0],
                               rtol=1e-4)
    density = -math.log(1 - 0.5 * MIN_OPACITY) / ray  # half the floor: the colour at the vertex
    np.testing.assert_allclose(normal_ray_colors(faint, v, n, half, samples, 100)[0], [0.0, 0.5, 0.0], atol=1e-7)


def test_point_colours_see_each_vertex_from_the_eye():
    seen = []

    def field(points: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        seen.append(dirs)
        return ((dirs + 1) / 2)[:, None, :].expand(-1, points.shape[1], 3), torch.ones(points.shape[:2])

    v = torch.tensor([[1.0, 2.0, 2.0], [0.0, -3.0, 4.0], [2.0, 0.0, 0.0]])
    eye = torch.tensor([0.0, 0.0, 0.0])
    got = point_colors(field, v, eye, chunk=2)
    np.testing.assert_allclose(got, (1 + v.numpy() / np.linalg.norm(v.numpy(), axis=1, keepdims=True)) / 2,
                               atol=1e-6)
    assert [len(d) for d in seen] == [2, 1]


def test_vertex_colors_are_rounded_rgba_and_rules_are_checked():
    def flat(points: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        rgb = torch.tensor([0.1, 0.504, 1.7]).expand(*points.shape[:2], 3)  # 1.7 is clipped
        return rgb, torch.full(points.shape[:2], 50.0)

    mesh = trimesh.Trimesh([[0, 0, 1], [1, 0, 1], [0, 1, 1]], [[0, 1, 2]], process=False)  # normals +z
    for rule in (NORMAL_RAY, POINT):
        rgba = mesh_colors.vertex_colors(rule, flat, mesh, torch.zeros(3), 0.05, 8, 64)
        assert rgba.dtype == np.uint8 and rgba.tolist() == [[26, 129, 255, 255]] * 3
    with pytest.raises(DepthnerfError, match="the photo rule needs the input photo"):
        mesh_colors.vertex_colors(PHOTO, flat, mesh, torch.zeros(3), 0.05, 8, 64)
    with pytest.raises(DepthnerfError, match="--mesh-colors must be one of normal-ray, photo, point, got 'vertex'"):
        mesh_colors.check_color_rule("vertex")
    with pytest.raises(DepthnerfError, match="--mesh-colors must be one of"):
        ReconstructConfig(mesh_colors="normal")
    with pytest.raises(DepthnerfError, match="half-width > 0 and >= 2 samples"):
        normal_ray_colors(flat, torch.zeros(1, 3), torch.ones(1, 3), 0.0, 8, 64)
    assert "0.06 outside" in mesh_colors.describe_colors(NORMAL_RAY, 0.06)
    assert "input camera" in mesh_colors.describe_colors(POINT, 0.06)
    assert "input photo" in mesh_colors.describe_colors(PHOTO, 0.06)
