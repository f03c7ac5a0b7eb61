"""The silhouette mesh level (depthnerf.render.mesh_level): the IoU search against a brute-force loop over every
candidate level, a closed form on a constant ball, and the case it exists for: thin parts that render opaque but
peak below half the typical density (a table's legs) are kept, where the auto level drops them."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from depthnerf.data.cameras import Intrinsics, look_at
from depthnerf.errors import DepthnerfError
from depthnerf.render.mesh import MeshConfig, source_mesh
from depthnerf.render.mesh_level import (
    DEFAULT_THRESHOLD,
    auto_level,
    input_ray_densities,
    levels_text,
    silhouette_choice,
    silhouette_level,
)

INTR = Intrinsics(focal=96.0, cx=31.5, cy=31.5, height=64, width=64)
NEAR, FAR = 1.0, 3.0


def _camera(azimuth: float = 0.3, elevation: float = 0.4) -> torch.Tensor:
    eye = 2.0 * torch.tensor([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                              np.sin(elevation)], dtype=torch.float32)
    return look_at(eye)


def brute_force_iou(peak: np.ndarray, opaque: np.ndarray, level: float) -> float:
    """IoU of {peak > level} with the opaque rays, one ray at a time."""
    inter = union = 0
    for p, o in zip(peak, opaque, strict=True):
        inside = p > level
        inter += int(inside and o)
        union += int(inside or o)
    return inter / union


@pytest.mark.parametrize("seed", range(6))
def test_silhouette_choice_is_the_best_level_of_a_brute_force_search(seed):
    rng = np.random.default_rng(seed)
    rays = 40
    peak = np.round(rng.gamma(2.0, 3.0, rays), 1)  # rounding makes ties between rays
    opaque = rng.random(rays) < np.clip(peak / peak.max() + rng.normal(0, 0.2, rays), 0, 1)
    opaque[np.argmax(peak)] = True  # at least one opaque ray
    level, iou = silhouette_choice(peak, opaque)
    values = np.unique(peak)
    candidates = np.concatenate([[0.0], (values[:-1] + values[1:]) / 2, [values[-1] + 1.0]])  # every distinct set
    best = max(brute_force_iou(peak, opaque, c) for c in candidates)
    assert iou == pytest.approx(best, abs=1e-12)
    assert brute_force_iou(peak, opaque, level) == pytest.approx(iou, abs=1e-12)  # the level keeps what it says
    assert all(brute_force_iou(peak, opaque, c) < best - 1e-12 for c in candidates if c > level)  # highest maximiser


def test_silhouette_choice_on_a_tie_and_when_every_ray_is_kept():
    """Hand-computed IoUs. Peaks 4 > 3 > 2 > 1 with targets on the 4 and the 1: keeping 1, 2, 3, 4 rays gives
    IoU 1/2, 1/3, 1/4, 2/4; the tie goes to the fewest rays kept, level (4 + 3) / 2. Every ray a target: all are
    kept (IoU 1) and the level is half the lowest peak, so the lowest ray is still inside ``{peak > level}``."""
    level, iou = silhouette_choice(np.array([2.0, 4.0, 1.0, 3.0]), np.array([False, True, True, False]))
    assert (level, iou) == (3.5, 0.5)
    peak = np.array([2.0, 5.0, 3.0])
    level, iou = silhouette_choice(peak, np.ones(3, dtype=bool))
    assert (level, iou) == (1.0, 1.0) and (peak > level).all()


def test_silhouette_level_stays_positive_when_rays_in_the_target_have_zero_peaks():
    """No positive level keeps a ray whose peak is 0, so keeping every ray is not a choice: with every ray a target,
    peaks 4, 2, 0, 0 give the two positive rays kept (IoU 2/4) at level 1, half the lowest kept peak."""
    peak, target = np.array([0.0, 4.0, 0.0, 2.0]), np.ones(4, dtype=bool)
    level, iou = silhouette_choice(peak, target)
    assert (level, iou) == (1.0, 0.5)
    assert brute_force_iou(peak, target, level) == pytest.approx(iou, abs=1e-12)


def test_local_level_of_a_ball_under_a_full_image_mask_is_a_mesh_of_the_ball():
    """A mask over the whole image, most of whose rays miss the ball (density 0 there): the silhouette level (the
    local rule's floor) stays positive, and the local mesh lies on the ball's falloff shell."""
    c2w, intr = _camera(), Intrinsics(focal=20.0, cx=7.5, cy=7.5, height=16, width=16)
    mask = np.ones((16, 16), dtype=bool)

    def density(p: torch.Tensor) -> torch.Tensor:  # 50 inside radius 0.25, falling linearly to 0 at 0.3
        return (50.0 * (0.3 - p.norm(dim=-1)) / 0.05).clamp(0.0, 50.0)

    level = silhouette_level(density, c2w, intr, NEAR, FAR, mask)
    assert level.level > 0 and level.iou < 1
    mesh, local = source_mesh(density, c2w, intr, NEAR, FAR, MeshConfig(resolution=48, threshold="local"),
                              mask=mask)
    radii = np.linalg.norm(mesh.vertices, axis=1)
    assert local.rule == "local" and local.floor > 0
    assert len(radii) and 0.25 - 0.02 < radii.min() and radii.max() < 0.3 + 0.02


def test_silhouette_level_of_a_constant_ball_is_half_its_density():
    def density(p: torch.Tensor) -> torch.Tensor:
        return torch.where(p.norm(dim=-1) < 0.5, torch.tensor(7.0), torch.tensor(0.0))

    c2w = _camera()
    level = silhouette_level(density, c2w, INTR, NEAR, FAR)
    peak, opacity = input_ray_densities(density, c2w, INTR, NEAR, FAR, ray_stride=1)
    hit, opaque = peak > 0, opacity > 0.5
    assert level.rule == "silhouette" and level.level == pytest.approx(3.5)  # midpoint of the peaks 7 and 0
    assert level.iou == pytest.approx(opaque.sum() / hit.sum())  # every hit ray kept; the grazing ones are not opaque
    assert level.opaque_rays == level.target_rays == opaque.sum() and level.rays == 64 * 64  # every pixel's ray
    assert level.describe().startswith(
        "silhouette level 3.5: its input-view silhouette matches the opaque input rays")
    assert "silhouette level per object" in levels_text([level], 48)


def table(top: float = 40.0, legs: float = 8.0):
    """A top (0.6 x 0.6 x 0.2, density ``top``) on four legs (radius 0.08, 0.4 long, density ``legs``), world z up."""
    def density(p: torch.Tensor) -> torch.Tensor:
        x, y, z = p.unbind(-1)
        board = (x.abs() < 0.3) & (y.abs() < 0.3) & (z > 0) & (z < 0.2)
        near_leg = ((x.abs() - 0.22) ** 2 + (y.abs() - 0.22) ** 2 < 0.08**2) & (z > -0.4) & (z <= 0)
        return torch.where(board, torch.tensor(top), torch.where(near_leg, torch.tensor(legs), torch.tensor(0.0)))
    return density


def test_thin_opaque_legs_are_kept_by_the_silhouette_level_and_dropped_by_auto():
    density, c2w = table(), _camera()
    peak, opacity = input_ray_densities(density, c2w, INTR, NEAR, FAR, ray_stride=1)
    legs_opaque = ((peak == 8.0) & (opacity > 0.5)).sum()
    assert legs_opaque > 20  # the legs render opaque on many rays ...
    auto = auto_level(density, c2w, INTR, NEAR, FAR)
    assert auto.level == pytest.approx(20.0)  # ... but peak at 8 < half the top's 40
    silhouette = silhouette_level(density, c2w, INTR, NEAR, FAR)
    assert silhouette.level < 8.0 and silhouette.iou > 0.9
    lowest = {}
    for rule in ("auto", "silhouette"):
        mesh, used = source_mesh(density, c2w, INTR, NEAR, FAR, MeshConfig(96, rule))
        assert used.rule == rule and len(mesh.faces) > 0
        lowest[rule] = mesh.vertices[:, 2].min()
    assert lowest["auto"] > -0.05  # the top alone
    assert lowest["silhouette"] < -0.35  # the legs down to their feet at z = -0.4


def test_soft_legs_are_kept_when_the_target_is_the_input_mask():
    density, c2w = table(legs=1.5), _camera()  # legs render half-transparent: 1.5 x (2 legs x 0.17) < ln 2
    peak, opacity = input_ray_densities(density, c2w, INTR, NEAR, FAR, ray_stride=1)
    assert not ((peak == 1.5) & (opacity > 0.5)).any()
    without = silhouette_level(density, c2w, INTR, NEAR, FAR)
    mask = (peak > 0).reshape(64, 64)  # the object's true silhouette: every ray that meets it
    with_mask = silhouette_level(density, c2w, INTR, NEAR, FAR, mask)
    assert without.level > 1.5 and with_mask.level < 1.5  # the rendered silhouette has no legs; the mask has
    assert (with_mask.target, with_mask.target_rays, with_mask.iou) == ("mask", mask.sum(), pytest.approx(1.0))
    assert "matches the input's mask" in with_mask.describe()
    mesh, used = source_mesh(density, c2w, INTR, NEAR, FAR, MeshConfig(96, "silhouette"), mask=mask)
    assert used == with_mask and mesh.vertices[:, 2].min() < -0.35
    with pytest.raises(DepthnerfError, match="mesh level: mask is 32x32 but the camera is 64x64"):
        silhouette_level(density, c2w, INTR, NEAR, FAR, mask[::2, ::2])
    empty = silhouette_level(density, c2w, INTR, NEAR, FAR, np.zeros_like(mask))
    assert (empty.rule, empty.level) == ("fallback", DEFAULT_THRESHOLD)
    assert empty.describe() == "silhouette level: the input's mask is empty, fell back to density 20"


def test_a_haze_that_does_not_render_opaque_stays_out():
    def density(p: torch.Tensor) -> torch.Tensor:
        ball = torch.where(p.norm(dim=-1) < 0.4, torch.tensor(30.0), torch.tensor(0.0))
        return ball + 0.3  # opacity of the haze alone over the 2-unit ray: 1 - e^-0.6 = 45% < 50%

    c2w = _camera()
    level = silhouette_level(density, c2w, INTR, NEAR, FAR)
    assert 0.3 < level.level < 30.3
    assert level.iou == pytest.approx(1.0)  # rays through the ball and only those


def test_silhouette_level_falls_back_without_opaque_rays():
    level = silhouette_level(lambda p: torch.full((len(p),), 0.1), _camera(), INTR, NEAR, FAR)
    assert (level.level, level.rule, level.iou) == (DEFAULT_THRESHOLD, "fallback", None)


def ball_and_rod(hard: bool = False):
    """A ball (radius 0.3, density 5, logistic edge of width 0.02 unless ``hard``) above a faint rod (radius 0.1,
    density 2, z from -0.6 to -0.25: at most 1 - e^-(2 x 0.2) = 33% opaque)."""
    def density(p: torch.Tensor) -> torch.Tensor:
        r = p.norm(dim=-1)
        ball = 5.0 * ((r < 0.3).float() if hard else torch.sigmoid((0.3 - r) / 0.02))
        x, y, z = p.unbind(-1)
        rod = 2.0 * ((x**2 + y**2 < 0.1**2) & (z > -0.6) & (z < -0.25)).float()
        return ball + rod
    return density


def test_local_level_keeps_the_faint_rod_and_the_half_maximum_sphere():
    c2w = _camera(elevation=0.0)
    hard_peak, _ = input_ray_densities(ball_and_rod(hard=True), c2w, INTR, NEAR, FAR, ray_stride=1)
    mask = (hard_peak > 0).reshape(64, 64)  # the true silhouette: ball and rod
    density, eye = ball_and_rod(), c2w[:3, 3].double().numpy()
    meshes = {rule: source_mesh(density, c2w, INTR, NEAR, FAR, MeshConfig(128, rule), mask=mask)
              for rule in ("auto", "silhouette", "local")}
    level = meshes["local"][1]
    assert level.rule == "local" and level.level == pytest.approx(2.5, rel=0.01)  # the auto level, as auto finds it
    assert level.level == pytest.approx(meshes["auto"][1].level) and level.floor == pytest.approx(
        meshes["silhouette"][1].level) and level.floor < 2.0  # the silhouette level lets the rod in
    assert "within" in level.describe() and "local level per object" in levels_text([level], 128)
    front = {}
    for rule, (mesh, _) in meshes.items():
        v = np.asarray(mesh.vertices)
        front[rule] = np.linalg.norm(v - eye, axis=1).min()  # nearest surface point: the sphere's front
        assert (v[:, 2].min() < -0.5) == (rule != "auto"), rule  # the rod, below the ball
    def radius(level: float) -> float:  # where 5 sigmoid((0.3 - r) / 0.02) = level
        return 0.3 + 0.02 * np.log(5.0 / level - 1.0)

    distance = np.linalg.norm(eye)
    assert front["auto"] == pytest.approx(distance - radius(meshes["auto"][1].level), abs=0.002)
    assert front["local"] == pytest.approx(distance - radius(level.level), abs=0.002)  # as tight as auto ...
    assert front["silhouette"] == pytest.approx(distance - radius(level.floor), abs=0.002)
    assert front["silhouette"] < front["local"] - 0.005  # ... where one low level inflates the ball


def test_local_level_is_the_auto_level_of_autos_rays_and_its_floor_never_exceeds_it():
    """A camera at the origin looking along +z through 8 x 8 pixels at a slab (camera z 1.5 to 2.5) of density
    40 on the even pixel columns and 10 on the odd ones. ``auto`` reads every 2nd row and column (even columns
    only): level 40 / 2 = 20 (the median over every ray would give 25 / 2). With the even columns as the mask
    the silhouette level is (40 + 10) / 2 = 25, above the auto level: the floor is then the auto level, 20."""
    from depthnerf.render.mesh_level import local_surface

    intr = Intrinsics(focal=8.0, cx=3.5, cy=3.5, height=8, width=8)

    def density(p: torch.Tensor) -> torch.Tensor:
        column = torch.round(p[:, 0] / p[:, 2] * intr.focal + intr.cx)
        slab = (p[:, 2] > 1.5) & (p[:, 2] < 2.5)
        return torch.where(slab, torch.where(column % 2 == 0, 40.0, 10.0), 0.0)

    mask = np.zeros((8, 8), dtype=bool)
    mask[:, ::2] = True
    assert auto_level(density, torch.eye(4), intr, NEAR, FAR).level == 20.0
    assert silhouette_level(density, torch.eye(4), intr, NEAR, FAR, mask).level == 25.0
    level, _, value = local_surface(density, torch.eye(4), intr, NEAR, FAR, mask)
    assert (level.rule, level.level, level.floor, level.iou, value) == ("local", 20.0, 20.0, 1.0, 1.0)


def test_local_level_falls_back_and_checks_the_mask():
    from depthnerf.render.mesh_level import local_surface

    flat = lambda p: torch.full((len(p),), 0.1)  # noqa: E731 - opacity 1 - e^-0.2: no opaque ray
    level, fn, value = local_surface(flat, _camera(), INTR, NEAR, FAR)
    assert (level.rule, level.level, value) == ("fallback", DEFAULT_THRESHOLD, DEFAULT_THRESHOLD) and fn is flat
    # a mask gives no auto level (its half median peak over the opaque rays) to clip to: still the fallback
    level, fn, value = local_surface(flat, _camera(), INTR, NEAR, FAR, np.ones((64, 64), bool))
    assert (level.rule, level.level, value) == ("fallback", DEFAULT_THRESHOLD, DEFAULT_THRESHOLD) and fn is flat
    with pytest.raises(DepthnerfError, match="mesh level: mask is 32x32 but the camera is 64x64"):
        local_surface(ball_and_rod(), _camera(), INTR, NEAR, FAR, np.ones((32, 32), bool))


def test_local_level_field_is_the_formula_at_pixel_centres():
    from depthnerf.data.cameras import camera_rays
    from depthnerf.render.mesh_level import local_surface

    c2w = _camera(elevation=0.0)
    hard_peak, _ = input_ray_densities(ball_and_rod(hard=True), c2w, INTR, NEAR, FAR, ray_stride=1)
    mask = (hard_peak > 0).reshape(64, 64)
    soft = ball_and_rod()

    def density(p: torch.Tensor) -> torch.Tensor:
        return soft(p) + 0.1  # a haze everywhere, so sigma / l is informative on background rays too

    level, fn, value = local_surface(density, c2w, INTR, NEAR, FAR, mask)
    peak, _ = input_ray_densities(density, c2w, INTR, NEAR, FAR, ray_stride=1)
    peak = peak.reshape(64, 64)
    origins, dirs = camera_rays(c2w, INTR)
    z_axis = c2w[:3, 2]
    for i, j in [(2, 3), (60, 5), (31, 31), *zip(*np.nonzero(mask & (peak < 2.3)), strict=True)]:
        depth = 1.7  # camera z of the probe point on pixel (i, j)'s ray
        point = origins[i, j] + dirs[i, j] * depth / float(dirs[i, j] @ z_axis)
        if mask[i, j]:
            expected = min(max(0.5 * peak[i, j], level.floor), level.level)
        else:
            expected = level.level  # background: the auto level, whatever the ray's peak
        got = float(fn(point[None])[0])
        assert got == pytest.approx(float(density(point[None])[0]) / expected, rel=1e-4), (i, j)
    assert value == 1.0 and mask.sum() > (mask & (peak < 2.3)).sum() > 0  # some rod rays were probed


def test_local_level_field_reads_its_own_pixel_of_a_wide_image():
    """A 40 x 24 camera at the origin looking along +z and a slab 1.9 < z < 2.1 whose density ``A`` varies with the
    ray (``x / z``, ``y / z``), so each ray's peak is its own ``A``. With the mask everywhere the levels are
    ``clip(0.5 A, 0.5 min A, 0.5 median A)``, and a point at a pixel centre is scaled by that pixel's level."""
    from depthnerf.data.cameras import camera_rays
    from depthnerf.render.mesh_level import local_surface

    intr = Intrinsics(focal=30.0, cx=19.5, cy=11.5, height=24, width=40)

    def density(p: torch.Tensor) -> torch.Tensor:
        a = 10 + 20 * (p[..., 0] / p[..., 2] + 0.7) + 10 * (p[..., 1] / p[..., 2] + 0.4)
        return torch.where((p[..., 2] - 2.0).abs() < 0.1, a, torch.zeros_like(a))

    c2w = torch.eye(4)
    level, fn, value = local_surface(density, c2w, intr, NEAR, FAR, np.ones((24, 40), bool))
    peak = input_ray_densities(density, c2w, intr, NEAR, FAR, ray_stride=1)[0].reshape(24, 40)
    assert (level.floor, level.level) == pytest.approx((0.5 * peak.min(), 0.5 * np.median(peak[::2, ::2])))
    origins, dirs = camera_rays(c2w, intr)
    for i, j in [(0, 0), (0, 39), (23, 0), (5, 10), (5, 30), (17, 8), (12, 20)]:
        point = origins[i, j] + dirs[i, j] * 2.0 / float(dirs[i, j, 2])
        expected = min(max(0.5 * peak[i, j], level.floor), level.level)
        assert float(fn(point[None])[0]) == pytest.approx(float(density(point[None])[0]) / expected, rel=1e-4)
    assert value == 1.0 and level.floor < 0.5 * peak[5, 10] < level.level  # a pixel with its own half-maximum
