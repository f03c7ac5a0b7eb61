"""The two framings of ``depthnerf synth``: SRN's numbers (spiral, view 64, radius, hemisphere, unit diagonal,
intrinsics, Blender pixel centres) and the legacy framing reproducing generator 1 (values from main's generator)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from depthnerf.data import srn_format
from depthnerf.data.cameras import Intrinsics, look_at, pixel_directions, project, world_to_camera
from depthnerf.data.card import dataset_pixel_center
from depthnerf.data.synth.cars import CAR_STYLES, HELDOUT_CAR_STYLES, build_car, sample_car
from depthnerf.data.synth.chairs import CHAIR_ARCHETYPES, HELDOUT_ARCHETYPES, build_chair, sample_chair
from depthnerf.data.synth.framing import FRAMINGS, checkpoint_framing, get_framing
from depthnerf.data.synth.generate import SynthConfig, category_spec, generate, object_poses, object_rngs
from depthnerf.data.synth.primitives import Material, MeshBuilder, box
from depthnerf.data.synth.raycast import PixelRays, Raycaster, SynthRenderConfig, render_view
from depthnerf.data.synth.views import poses_from_angles, srn_spiral_angles
from depthnerf.errors import DepthnerfError


def _renderer_spiral(radius: float, num_steps: int = 250) -> np.ndarray:
    """SRN's spiral as its renderer's loop runs it (float accumulation included), in SRN's +y-up world:
    polar angle i/40*pi, azimuth -i, i from 20 in steps of 40/(2*num_steps) while i < 40."""
    a, out, i = 40.0, [], 20.0
    while i < a:
        theta = i / a * math.pi
        out.append((radius * math.sin(theta) * math.cos(-i), -radius * math.cos(theta),
                    radius * math.sin(math.pi - theta) * math.sin(-i)))
        i += a / (2 * num_steps)
    return np.array(out)


def _srn_to_depthnerf(xyz: np.ndarray) -> np.ndarray:
    """SRN world (x, y, z) -> depthnerf world (-z, -x, y): ShapeNet's front -Z -> +x, up +Y -> +z."""
    return np.stack([-xyz[:, 2], -xyz[:, 0], xyz[:, 1]], axis=1)


@pytest.mark.parametrize("category", ["cars", "chairs"])
def test_srn_spiral_is_the_renderers(category: str) -> None:
    spec = category_spec(category, "srn")
    ref = _srn_to_depthnerf(_renderer_spiral(spec.radius))
    assert len(ref) == 251
    poses = object_poses("test", 251, spec, np.random.default_rng(0))
    np.testing.assert_allclose(poses[:, :3, 3], ref, atol=1e-5)
    np.testing.assert_allclose(poses[:, :3, 2], -ref / spec.radius, atol=1e-5)  # looking at the origin
    assert spec.radius == {"cars": 1.3, "chairs": 2.0}[category]
    elevation = np.degrees(np.arcsin(poses[:, 2, 3] / spec.radius))
    assert elevation[0] == pytest.approx(0.0, abs=1e-4) and elevation[-1] == pytest.approx(90.0, abs=1e-3)


def test_srn_view64_is_side_view() -> None:
    elevation, azimuth = srn_spiral_angles(251)
    assert math.degrees(elevation[64]) == pytest.approx(23.04, abs=1e-9)
    assert math.degrees(azimuth[64]) % 360 == pytest.approx(269.27, abs=0.01)
    car = build_car(sample_car(np.random.default_rng(7)))
    extent = np.ptp(car.vertices, axis=0)
    assert np.argmax(extent) == 0  # the car's length lies along +x, as ShapeNet's front -Z maps to +x
    for framing, lo, hi in (("srn", 89.0, 90.0), ("legacy", 0.0, 70.0)):
        forward = object_poses("test", 251, category_spec("cars", framing), np.random.default_rng(0))[64, :3, 2]
        angle = math.degrees(math.acos(abs(float(forward[0]))))  # viewing direction vs the length axis
        assert lo <= angle <= hi, (framing, angle)


def test_srn_train_views_area_uniform_upper_hemisphere() -> None:
    spec = category_spec("chairs", "srn")
    eyes = np.concatenate([object_poses("train", 50, spec, object_rngs(0, "chairs", "train", k)[1])[:, :3, 3]
                           for k in range(400)])
    np.testing.assert_allclose(np.linalg.norm(eyes, axis=1), 2.0, rtol=1e-6)
    u = eyes[:, 2] / 2.0
    assert u.min() >= -1e-7
    hist, _ = np.histogram(u, bins=10, range=(0, 1))  # z uniform in [0, r]: area-uniform up to the pole
    np.testing.assert_allclose(hist / len(u), 0.1, atol=0.01)


def test_poses_from_angles_match_look_at_and_define_the_pole() -> None:
    el = np.radians([0.0, 23.0, 60.0, 89.0])
    az = np.radians([10.0, 200.0, -45.0, 123.0])
    ours = poses_from_angles(1.3, el, az)
    ref = look_at(torch.from_numpy(ours[:, :3, 3].astype(np.float64)).float()).numpy()
    np.testing.assert_allclose(ours, ref, atol=1e-5)
    pole = poses_from_angles(2.0, np.array([math.pi / 2]), np.array([0.3]))[0].astype(np.float64)
    np.testing.assert_allclose(pole[:3, :3].T @ pole[:3, :3], np.eye(3), atol=1e-6)
    np.testing.assert_allclose(pole[:3, 2], [0, 0, -1], atol=1e-6)
    np.testing.assert_allclose(pole[:3, 0], [-math.sin(0.3), math.cos(0.3), 0], atol=1e-6)


@pytest.mark.parametrize("framing, chair_diagonal", [("srn", 1.0), ("legacy", 1.35)])
def test_object_size(framing: str, chair_diagonal: float) -> None:
    rng = np.random.default_rng(3)
    assert category_spec("cars", framing).diagonal == 1.0
    assert category_spec("chairs", framing).diagonal == chair_diagonal
    chair = build_chair(sample_chair(rng), category_spec("chairs", framing).diagonal)
    lo, hi = chair.vertices.min(0), chair.vertices.max(0)
    assert np.linalg.norm(hi - lo) == pytest.approx(chair_diagonal)
    np.testing.assert_allclose((lo + hi) / 2, 0.0, atol=1e-12)  # bounding box centred, as SRN's renderer does


def test_srn_intrinsics_as_blender_writes_them() -> None:
    fr = get_framing("srn")
    assert fr.file_intrinsics(128) == Intrinsics(131.25, 64.0, 64.0, 128, 128)
    assert fr.file_intrinsics(64) == Intrinsics(65.625, 32.0, 32.0, 64, 64)
    assert fr.render_intrinsics(64) == Intrinsics(65.625, 31.5, 31.5, 64, 64)
    # reading the 128 px file with Blender's centres and resizing = the 64 px file read the same way
    assert fr.file_intrinsics(128).with_pixel_center(0.5).resized(64, 64) == fr.render_intrinsics(64)
    legacy = get_framing("legacy")
    assert legacy.file_intrinsics(64) == legacy.render_intrinsics(64) == Intrinsics(65.625, 31.75, 31.75, 64, 64)
    with pytest.raises(DepthnerfError, match="unknown framing"):
        get_framing("blender")


@pytest.mark.parametrize("framing", ["srn", "legacy"])
def test_depth_of_a_tilted_plane_is_analytic_at_the_framings_pixel_centres(framing: str) -> None:
    """A flat box top (z = h) seen obliquely: the rendered z-depth of pixel (i, j) equals the analytic depth of the
    ray through (j + c, i + c) of the written intrinsics, c = 0.5 (SRN) or 0 (legacy); the other c is wrong."""
    b = MeshBuilder()
    b.add(box((1.0, 1.0, 0.05)), Material("test", (0.5, 0.5, 0.5)))
    mesh = b.build(diagonal=math.sqrt(2.0025))  # keeps the 1 x 1 x 0.05 size
    h = float(mesh.vertices[:, 2].max())
    fr = get_framing(framing)
    res = 40
    c2w = poses_from_angles(1.3, np.radians([50.0]), np.radians([20.0]))[0]
    view = render_view(Raycaster(mesh), c2w, PixelRays(fr.render_intrinsics(res)), SynthRenderConfig(antialias=False))
    file_intr = fr.file_intrinsics(res)
    rot, eye = c2w[:3, :3].astype(np.float64), c2w[:3, 3].astype(np.float64)
    depth, inside = {}, None
    for c in (0.0, 0.5):
        jj, ii = np.meshgrid(np.arange(res) + c, np.arange(res) + c)
        d_cam = np.stack([(jj - file_intr.cx) / file_intr.focal, (ii - file_intr.cy) / file_intr.focal,
                          np.ones_like(jj)], -1)  # z = 1: the ray parameter is the z-depth
        d_world = d_cam @ rot.T
        depth[c] = (h - eye[2]) / d_world[..., 2]
        hit = eye + depth[c][..., None] * d_world
        if c == fr.pixel_center:  # pixels well inside the top face
            inside = (np.abs(hit[..., 0]) < 0.45) & (np.abs(hit[..., 1]) < 0.45) & (depth[c] > 0)
    assert inside.sum() > 200 and view.mask[inside].all()
    errors = {c: float(np.abs(view.depth[inside] - z[inside]).max()) for c, z in depth.items()}
    assert errors[fr.pixel_center] < 1e-5
    assert errors[0.5 - fr.pixel_center] > 1e-3


def test_pixel_center_is_a_principal_point_shift() -> None:
    """Rays and projections with ``with_pixel_center(c)`` equal a brute-force loop over pixel centres (j+c, i+c)."""
    intr = Intrinsics(focal=40.0, cx=12.0, cy=9.0, height=18, width=24)
    for c in (0.0, 0.5, 0.25):
        shifted = intr.with_pixel_center(c)
        dirs = pixel_directions(shifted, normalize=False).numpy()
        for i in range(intr.height):
            for j in range(intr.width):
                ref = [(j + c - intr.cx) / intr.focal, (i + c - intr.cy) / intr.focal, 1.0]
                np.testing.assert_allclose(dirs[i, j], ref, atol=1e-6)
        # a camera point on the ray of pixel (i, j) projects back to (j, i) with the shifted principal point
        pts = torch.from_numpy(dirs.reshape(-1, 3) * 1.7)
        uv = project(pts, shifted.focal, (shifted.cx, shifted.cy)).numpy()
        jj, ii = np.meshgrid(np.arange(intr.width), np.arange(intr.height))
        np.testing.assert_allclose(uv, np.stack([jj.ravel(), ii.ravel()], 1), atol=1e-4)


def test_load_object_applies_the_pixel_center_before_resizing(tmp_path: Path) -> None:
    """SRN-framed data at 32 px loaded at 16 px with pixel_center 0.5: the ray of pixel (i, j) goes through the
    centre of its 2 x 2 block of file pixels, i.e. file coordinates (2j + 1, 2i + 1); with 0.0 it does not."""
    from depthnerf.data.srn import index_split, load_object

    generate(SynthConfig(category="cars", out=tmp_path, train_objects=0, val_objects=0, test_objects=1,
                         resolution=32, views_test=3, progress=False))
    record = index_split(tmp_path, "cars", "test").objects[0]
    file_intr = record.intrinsics
    jj, ii = np.meshgrid(np.arange(16), np.arange(16))
    ref = np.stack([(2 * jj + 1 - file_intr.cx) / file_intr.focal, (2 * ii + 1 - file_intr.cy) / file_intr.focal,
                    np.ones_like(jj, dtype=np.float64)], -1)
    good = load_object(record, [0], resolution=16, pixel_center=0.5).intrinsics
    np.testing.assert_allclose(pixel_directions(good, normalize=False).numpy(), ref, atol=1e-6)
    bad = load_object(record, [0], resolution=16, pixel_center=0.0).intrinsics
    assert np.abs(pixel_directions(bad, normalize=False).numpy() - ref).max() > 0.1 / file_intr.focal
    assert dataset_pixel_center(tmp_path, "cars") == 0.5 and dataset_pixel_center(tmp_path, "chairs") == 0.0


# main's generator (depthnerf-synth-1, before the framings existed) on the config of ``_legacy_config``:
# faces, bounding box, and per view (pose rows 0-2, RGB mean, mask pixels, depth sum)
LEGACY_GOLDEN = {
    "cars_test": (9406, [-0.443561, -0.191728, -0.128428, 0.443561, 0.191728, 0.128428], {
        "000064": ([-0.906308, 0.419051, -0.054792, 0.071229, 0.422618, 0.898659, -0.117501, 0.152752, 0.0,
                    -0.129648, -0.99156, 1.289028], 0.859073, 108, 134.2352)}),
    "cars_train": (9406, [-0.435549, -0.194617, -0.149737, 0.435549, 0.194617, 0.149737], {
        "000000": ([0.960831, 0.261641, -0.091369, 0.11878, 0.277136, -0.907109, 0.316778, -0.411811, -0.0,
                    -0.329692, -0.944089, 1.227315], 0.903701, 116, 139.1818)}),
    "chairs_test": (844, [-0.311196, -0.282641, -0.528106, 0.311196, 0.282641, 0.528106], {
        "000064": ([-0.906308, 0.419051, -0.054792, 0.109584, 0.422618, 0.898659, -0.117501, 0.235003, 0.0,
                    -0.129648, -0.99156, 1.98312], 0.90497, 61, 115.5871)}),
    "chairs_train": (1936, [-0.278342, -0.249703, -0.56196, 0.278342, 0.249703, 0.56196], {
        "000002": ([-0.807148, -0.043424, 0.58875, -1.177501, -0.59035, 0.059371, -0.804961, 1.609922, 0.0,
                    -0.997291, -0.073556, 0.147112], 0.950561, 49, 90.6365)}),
}
"""Measured with main's ``generate`` at commit 9c03ce6 (this test's config)."""


def test_legacy_framing_reproduces_generator_1(tmp_path: Path) -> None:
    for category in ("cars", "chairs"):
        card = generate(SynthConfig(category=category, out=tmp_path, train_objects=1, val_objects=0,
                                    test_objects=1, resolution=24, views_train=3, views_test=70, seed=5,
                                    progress=False, framing="legacy"))
        assert card["generator"] == f"depthnerf-synth-1/{category}-r2" and card["framing"] == "legacy"
    for folder, (faces, bbox, views) in LEGACY_GOLDEN.items():
        obj = next((tmp_path / folder).iterdir())
        assert (obj / "intrinsics.txt").read_text().split()[:3] == ["24.609375", "11.593750", "11.593750"]
        marker = json.loads((obj / ".synth_done.json").read_text())
        assert marker["faces"] == faces
        np.testing.assert_allclose(marker["bbox_min"] + marker["bbox_max"], bbox, atol=2e-6)
        for name, (pose, rgb_mean, mask_pixels, depth_sum) in views.items():
            np.testing.assert_allclose(srn_format.read_pose(obj / "pose" / f"{name}.txt")[:3].ravel(), pose,
                                       atol=2e-6)
            mask = srn_format.read_mask(obj / "mask" / f"{name}.png")
            assert abs(int(mask.sum()) - mask_pixels) <= 1
            assert float(srn_format.read_rgb(obj / "rgb" / f"{name}.png").mean()) == pytest.approx(rgb_mean, abs=2e-3)
            assert float(srn_format.read_depth(obj / "depth" / f"{name}.npz").sum()) == pytest.approx(depth_sum,
                                                                                                     abs=2.0)


def test_heldout_family_differs_from_the_standard_one() -> None:
    rng = np.random.default_rng(0)
    standard = [sample_chair(rng) for _ in range(600)]
    heldout = [sample_chair(rng, family="heldout") for _ in range(200)]
    assert {c.archetype for c in heldout} == set(HELDOUT_ARCHETYPES) and not set(HELDOUT_ARCHETYPES) & set(
        CHAIR_ARCHETYPES)
    pairs = {(c.legs, c.back) for c in standard}
    held_pairs = {(c.legs, c.back) for c in heldout}
    assert len(held_pairs) >= 6 and not held_pairs & pairs  # leg/back mixes the standard family never builds
    cars = [sample_car(rng) for _ in range(300)]
    micro = [sample_car(rng, family="heldout") for _ in range(50)]
    assert {c.style for c in micro} == set(HELDOUT_CAR_STYLES) and not set(HELDOUT_CAR_STYLES) & set(CAR_STYLES)
    assert min(c.dims["roof"] for c in micro) > max(c.dims["roof"] for c in cars)  # taller than any standard car
    with pytest.raises(DepthnerfError, match="unknown family"):
        generate(SynthConfig(category="cars", out=Path("unused"), family="exotic"))


def test_checkpoint_framing_lookup(tmp_path: Path) -> None:
    weights = tmp_path / "ck.safetensors"
    assert checkpoint_framing(weights, None, "cars")[0] == "srn"  # nothing known: the default
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "cars_card.json").write_text(json.dumps({"generator": "depthnerf-synth-1/cars-r2"}))
    assert checkpoint_framing(weights, tmp_path / "data", "cars")[0] == "legacy"  # a card before framings
    (tmp_path / "ck.json").write_text(json.dumps({"framing": "srn"}))
    framing, source = checkpoint_framing(weights, tmp_path / "data", "cars")
    assert framing == "srn" and source.endswith("ck.json")
    shipped = Path(__file__).resolve().parent.parent / "depthnerf" / "checkpoints"
    for card in sorted(shipped.glob("cpu-*.json")):
        assert checkpoint_framing(card.with_suffix(".safetensors"), None, "cars")[0] == "srn", card
    assert set(FRAMINGS) == {"srn", "legacy"}


@pytest.mark.parametrize("framing", sorted(FRAMINGS))
@pytest.mark.parametrize("category", ["cars", "chairs"])
def test_framing_fill_is_the_generators(framing: str, category: str) -> None:
    """``Framing.fill`` (the photo framing of models trained on this data) is the median, over the train views of
    6 objects, of the longer side of the silhouette's bounding box over the image side. The silhouette's box is
    that of the projected mesh vertices, so this needs no rendering (``scripts/measure_fill.py`` renders masks)."""
    spec, intr = category_spec(category, framing), get_framing(framing).file_intrinsics(128)
    fills = []
    for index in range(6):
        shape_rng, view_rng = object_rngs(0, category, "train", index)
        mesh = build_car(sample_car(shape_rng)) if category == "cars" else \
            build_chair(sample_chair(shape_rng), spec.diagonal)
        verts = torch.as_tensor(mesh.vertices, dtype=torch.float64)
        for c2w in torch.as_tensor(object_poses("train", 50, spec, view_rng), dtype=torch.float64):
            uv = project(world_to_camera(verts, c2w), intr.focal, (intr.cx, intr.cy))
            fills.append(float((uv.amax(0) - uv.amin(0)).max()) / 128)
    assert get_framing(framing).fill(category, 0.0) == pytest.approx(float(np.median(fills)), abs=0.02)
