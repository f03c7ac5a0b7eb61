"""The SRN reader (depthnerf.data.srn) against hand-made real-format folders and brute-force references."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from fixtures_srn import (
    BAD_INPUT_CASES,
    CAMERA_RADIUS,
    STYLES,
    first_object,
    fixture_intrinsics,
    fixture_pose,
    make_srn_fixture,
    object_id,
    render_sphere,
    sphere_radius,
    to_srn_style,
)
from PIL import Image

from depthnerf.data import srn, srn_format
from depthnerf.data.cameras import (
    Intrinsics,
    backproject,
    look_at,
    pixel_directions,
    project,
    world_to_camera,
)
from depthnerf.errors import DepthnerfError


def test_category_defaults_registry():
    cars, chairs = srn.category_defaults("cars"), srn.category_defaults("chairs")
    assert (cars.z_near, cars.z_far, cars.camera_radius, cars.focal, cars.image_size) == (0.8, 1.8, 1.3, 131.25, 128)
    assert (chairs.z_near, chairs.z_far, chairs.camera_radius, chairs.focal) == (1.25, 2.75, 2.0, 131.25)
    with pytest.raises(TypeError):
        srn.CATEGORY_DEFAULTS["planes"] = cars  # read-only mapping
    with pytest.raises(DepthnerfError, match=r"unknown SRN category 'planes'.*still loads.*z_near, z_far"):
        srn.category_defaults("planes")


def test_index_and_load_match_what_was_written(srn_root_full: Path):
    index = srn.index_split(srn_root_full, "cars", "train")
    assert [o.object_id for o in index.objects] == sorted(o.object_id for o in index.objects)
    assert len(index.objects) == 2 and index.skipped == [] and set(index.checks) == {o.object_id for o in index.objects}
    rec = index.objects[0]
    assert rec.view_names == ("000000", "000001", "000002") and rec.num_views == 3
    assert rec.intrinsics == fixture_intrinsics(16)
    assert rec.has_depth and rec.has_mask and rec.mesh_path == rec.path / "mesh.ply"
    assert rec.rgb_path(2) == rec.path / "rgb" / "000002.png" and rec.pose_path(0).suffix == ".txt"
    assert index.checks[rec.object_id].radius_min == pytest.approx(1.3, abs=1e-6)

    views = srn.load_object(rec, with_depth=True, pixel_center=0.0)
    assert views.images.shape == (3, 3, 16, 16) and views.images.dtype == torch.float32
    assert views.view_indices.tolist() == [0, 1, 2] and views.intrinsics == rec.intrinsics
    k = [object_id("cars", "train", i) for i in range(2)].index(rec.object_id)
    tint = np.random.default_rng(k).uniform(0.5, 1.0, size=3)
    for v in range(3):
        pose = fixture_pose(v, 3, CAMERA_RADIUS["cars"], phase=0.7 * k)
        rgb, mask, depth = render_sphere(pose, rec.intrinsics, sphere_radius(1.3), tint)
        assert torch.equal(views.images[v], torch.from_numpy(rgb).permute(2, 0, 1).float() / 255)
        assert torch.allclose(views.poses[v], torch.from_numpy(pose), atol=1e-7)
        assert torch.equal(views.masks[v], torch.from_numpy(mask)) and torch.equal(views.depths[v], torch.from_numpy(depth))


def test_depth_pose_intrinsics_conventions_agree(srn_root_full: Path):
    """Back-projecting every z-depth pixel with the loaded intrinsics and pose lands on the sphere."""
    rec = srn.index_split(srn_root_full, "cars", "test").objects[0]
    views = srn.load_object(rec, with_depth=True, pixel_center=0.0)
    rays = pixel_directions(views.intrinsics, normalize=False)  # z == 1, so z-depth scales it to the point
    for v in range(rec.num_views):
        pts_cam = rays[views.masks[v]] * views.depths[v][views.masks[v], None]
        pts = pts_cam @ views.poses[v, :3, :3].T + views.poses[v, :3, 3]
        assert torch.allclose(pts.norm(dim=-1), torch.tensor(sphere_radius(1.3)), atol=1e-5)


def _png_format(path: Path) -> tuple[int, int]:
    """(bit depth, colour type) from the PNG's IHDR chunk (colour type 2 = RGB, 6 = RGBA)."""
    data = path.read_bytes()
    return data[24], data[25]


def test_real_srn_style_loads_identically(tmp_path: Path):
    root = make_srn_fixture(tmp_path / "a", splits={"test": 1}, views=4, size=128, with_depth=True)
    src = first_object(root, split="test")
    dst = to_srn_style(src, tmp_path / "b" / "cars_test" / src.name)
    assert (dst / "intrinsics.txt").read_text() == "131.25 64. 64. 0.\n0. 0. 0.\n1.\n128 128\n"
    assert len((dst / "pose" / "000000.txt").read_text().split("\n")[0].split()) == 4
    assert STYLES == ("rgba8", "rgb16", "rgba16")
    assert [_png_format(dst / "rgb" / f"{v:06d}.png") for v in range(4)] == [(8, 6), (16, 2), (16, 6), (8, 6)]
    a = srn.load_object(srn.index_object(src, "cars", "test"), with_depth=True, pixel_center=0.0)
    b = srn.load_object(srn.index_split(tmp_path / "b", "cars", "test").objects[0], with_depth=True, pixel_center=0.0)
    assert a.intrinsics == b.intrinsics == Intrinsics(131.25, 64.0, 64.0, 128, 128)
    for name in ("images", "poses", "masks", "bboxes", "depths", "view_indices"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert a.masks.any() and not a.masks.all()


def test_16bit_grey_png_full_precision(tmp_path: Path):
    obj = first_object(make_srn_fixture(tmp_path, splits={"train": 1}, views=1))
    grey = np.arange(256, dtype=np.uint16).reshape(16, 16) * 257 + np.arange(16, dtype=np.uint16)[:, None]
    grey[0, 0] = 65535
    Image.fromarray(grey).save(obj / "rgb" / "000000.png")
    assert Image.open(obj / "rgb" / "000000.png").mode.startswith("I;16")
    views = srn.load_object(srn.index_object(obj, "cars", "train"), pixel_center=0.0)
    expected = torch.from_numpy(grey.astype(np.float32) / 65535).expand(3, 16, 16)
    assert torch.equal(views.images[0], expected)
    assert not views.masks[0, 0, 0] and views.masks[0].sum() == 255  # only the 65535 pixel is white


def test_chairs_train_nesting(tmp_path: Path):
    root = make_srn_fixture(tmp_path, category="chairs", splits={"train": 2, "test": 1})
    assert (root / "chairs_train" / "chairs_2.0_train").is_dir()
    assert srn.split_dir(root, "chairs", "train") == root / "chairs_train" / "chairs_2.0_train"
    assert srn.split_dir(root, "chairs", "test") == root / "chairs_test"
    index = srn.index_split(root, "chairs", "train")
    assert index.path == root / "chairs_train" / "chairs_2.0_train" and len(index.objects) == 2
    assert index.objects[0].path.parent.name == "chairs_2.0_train"
    assert index.checks[index.objects[0].object_id].radius_max == pytest.approx(2.0, abs=1e-6)
    assert srn.discover_categories(root) == ["chairs"]


def test_discover_categories_ignores_other_folders(tmp_path: Path):
    make_srn_fixture(tmp_path, splits={"train": 1})
    make_srn_fixture(tmp_path, category="chairs", splits={"val": 1})
    for name in ("notes", "cars_extra", ".cache_test"):
        (tmp_path / name).mkdir()
    (tmp_path / "planes_test.zip").write_text("")
    assert srn.discover_categories(tmp_path) == ["cars", "chairs"]
    with pytest.raises(DepthnerfError, match="does not exist"):
        srn.discover_categories(tmp_path / "nope")


def test_split_ignores_macos_zip_residue_and_hidden_folders(tmp_path: Path):
    """``__MACOSX/`` (what macOS's zip leaves beside the archived folders) and hidden folders inside a split folder
    are not objects; any other folder without intrinsics.txt still is, and is an error."""
    root = make_srn_fixture(tmp_path, splits={"test": 2})
    ids = sorted(p.name for p in (root / "cars_test").iterdir())
    for residue in ("__MACOSX", ".Trash"):
        obj = root / "cars_test" / residue / ids[0]
        (obj / "rgb").mkdir(parents=True)
        (obj / "._intrinsics.txt").write_bytes(b"\x00\x05\x16\x07")  # AppleDouble header, not intrinsics
    index = srn.index_split(root, "cars", "test")
    assert [o.object_id for o in index.objects] == ids and not index.skipped
    (root / "cars_test" / "MACOSX").mkdir()
    with pytest.raises(DepthnerfError, match=r"MACOSX/intrinsics\.txt"):
        srn.index_split(root, "cars", "test")


def _block_object(tmp_path: Path, size: int = 64) -> srn.ObjectRecord:
    """One white 64x64 view (SRN-style intrinsics) with a black 4x4 block at rows 8-11, columns 20-23."""
    obj = first_object(make_srn_fixture(tmp_path, splits={"train": 1}, views=1, size=size))
    img = np.full((size, size, 3), 255, dtype=np.uint8)
    img[8:12, 20:24] = 0
    srn_format.write_rgb(obj / "rgb" / "000000.png", img)
    return srn.index_object(obj, "cars", "train")


@pytest.mark.parametrize("resolution", [16, 32, 128])
def test_resize_rescales_intrinsics_like_a_projected_point(tmp_path: Path, resolution: int):
    rec = _block_object(tmp_path)
    full = srn.load_object(rec, pixel_center=0.0)
    # The world point seen at the block's centre (u, v) = (21.5, 9.5), 1.1 in front of the camera.
    intr, c2w = full.intrinsics, full.poses[0]
    p_cam = torch.tensor([(21.5 - intr.cx) / intr.focal, (9.5 - intr.cy) / intr.focal, 1.0]) * 1.1
    p_world = c2w[:3, :3] @ p_cam + c2w[:3, 3]
    small = srn.load_object(rec, resolution=resolution, pixel_center=0.0)
    s = resolution / 64
    assert small.images.shape == (1, 3, resolution, resolution)
    assert small.intrinsics.focal == pytest.approx(intr.focal * s)
    uv = project(world_to_camera(p_world[None], small.poses[0]), small.intrinsics.focal,
                 (small.intrinsics.cx, small.intrinsics.cy))[0]
    # The block covers rows [8, 12) and columns [20, 24) in continuous coordinates -> scaled by s.
    rows, cols = slice(int(8 * s), int(12 * s)), slice(int(20 * s), int(24 * s))
    assert torch.allclose(uv, torch.tensor([(22 * s) - 0.5, (10 * s) - 0.5]), atol=1e-4)
    assert torch.all(small.images[0, :, rows, cols] == 0)
    assert small.images[0].sum() == 3 * (resolution**2 - (4 * s) ** 2)  # the rest is exactly white
    assert small.bboxes[0].tolist() == [cols.start, rows.start, cols.stop - 1, rows.stop - 1]


def _brute_mask_and_box(img8: np.ndarray) -> tuple[np.ndarray, list[int]]:
    height, width, _ = img8.shape
    mask = np.zeros((height, width), dtype=bool)
    for i in range(height):
        for j in range(width):
            mask[i, j] = all(int(img8[i, j, c]) != 255 for c in range(3))
    rows = [i for i in range(height) if any(mask[i, j] for j in range(width))]
    cols = [j for j in range(width) if any(mask[i, j] for i in range(height))]
    box = [cols[0], rows[0], cols[-1], rows[-1]] if rows else [0, 0, width - 1, height - 1]
    return mask, box


def test_mask_and_bbox_match_brute_force(tmp_path: Path):
    obj = first_object(make_srn_fixture(tmp_path, splits={"train": 1}, views=4, size=12))
    rng = np.random.default_rng(3)
    images = []
    for v in range(4):
        img = np.full((12, 12, 3), 255, dtype=np.uint8)
        if v < 3:  # sparse non-white pixels, some white in only one or two channels
            img[rng.random((12, 12)) < 0.08] = rng.integers(0, 256, size=3, dtype=np.uint8)
            img[rng.random((12, 12)) < 0.1, rng.integers(0, 3)] = 254
        images.append(img)  # view 3: all white (SRN cars test has such a view)
        srn_format.write_rgb(obj / "rgb" / f"{v:06d}.png", img)
    rgba = np.concatenate([images[2], np.full((12, 12, 1), 255, np.uint8)], axis=-1)
    Image.fromarray(rgba, mode="RGBA").save(obj / "rgb" / "000002.png")
    views = srn.load_object(srn.index_object(obj, "cars", "train"), pixel_center=0.0)
    for v in range(4):
        mask, box = _brute_mask_and_box(images[v])
        assert torch.equal(views.masks[v], torch.from_numpy(mask)) and views.bboxes[v].tolist() == box
    assert not views.masks[3].any() and views.bboxes[3].tolist() == [0, 0, 11, 11]
    assert views.bboxes.dtype == torch.int64
    half = srn.load_object(srn.index_object(obj, "cars", "train"), resolution=6, pixel_center=0.0)
    for v in range(4):  # a 2x2 block is object if any of its pixels is
        mask, _ = _brute_mask_and_box(images[v])
        ref = np.array([[mask[2 * i:2 * i + 2, 2 * j:2 * j + 2].any() for j in range(6)] for i in range(6)])
        assert torch.equal(half.masks[v], torch.from_numpy(ref))
        rows, cols = np.nonzero(ref.any(1))[0], np.nonzero(ref.any(0))[0]
        box = [cols[0], rows[0], cols[-1], rows[-1]] if len(rows) else [0, 0, 5, 5]
        assert half.bboxes[v].tolist() == box


def test_depth_resize_averages_valid_depths_only(srn_root_full: Path):
    rec = srn.index_split(srn_root_full, "cars", "train").objects[1]
    full = srn.load_object(rec, with_depth=True, pixel_center=0.0)
    half = srn.load_object(rec, with_depth=True, resolution=8, pixel_center=0.0)
    for v in range(rec.num_views):
        d = full.depths[v].numpy()
        for i in range(8):
            for j in range(8):
                block = d[2 * i:2 * i + 2, 2 * j:2 * j + 2]
                ref = block[block > 0].mean() if (block > 0).any() else 0.0
                assert half.depths[v, i, j].item() == pytest.approx(ref, rel=1e-6)
        assert torch.equal(half.depths[v] > 0, half.masks[v])


def test_view_selection_and_request_errors(srn_root: Path):
    rec = srn.index_split(srn_root, "cars", "train", check_files=False).objects[0]
    assert srn.index_split(srn_root, "cars", "train", check_files=False).checks == {}
    full = srn.load_object(rec, pixel_center=0.0)
    some = srn.load_object(rec, views=[2, 0], pixel_center=0.0)
    assert some.view_indices.tolist() == [2, 0]
    assert torch.equal(some.images, full.images[[2, 0]]) and torch.equal(some.poses, full.poses[[2, 0]])
    with pytest.raises(DepthnerfError, match="view index 3 out of range"):
        srn.load_object(rec, views=[0, 3], pixel_center=0.0)
    with pytest.raises(DepthnerfError, match="no depth/ folder"):
        srn.load_object(rec, with_depth=True, pixel_center=0.0)
    with pytest.raises(DepthnerfError, match="cannot resize 16x16 images to height 0"):
        srn.load_object(rec, resolution=0, pixel_center=0.0)


def test_check_size_false_rescales_intrinsics(srn_root: Path):
    rec = srn.index_split(srn_root, "cars", "test").objects[0]
    for v in range(rec.num_views):  # the images were resampled to 32x32 after the intrinsics were written
        img = srn_format.read_rgb(rec.rgb_path(v))
        srn_format.write_rgb(rec.rgb_path(v), img.repeat(2, axis=0).repeat(2, axis=1))
    with pytest.raises(DepthnerfError, match=r"000000\.png: image is 32x32 but .*intrinsics\.txt says 16x16"):
        srn.load_object(rec, pixel_center=0.0)
    views = srn.load_object(rec, check_size=False, pixel_center=0.0)
    assert views.images.shape[-2:] == (32, 32) and views.intrinsics == rec.intrinsics.resized(32, 32)


def test_intrinsics_and_pose_files_read_as_the_format_states(tmp_path: Path):
    """``intrinsics.txt``: ``f cx cy 0.`` first, ``H W`` on the last line, so a non-square image with cx != cy
    keeps each number in its place, a file with an extra line before the size reads the same, and the writer
    puts ``H W`` last. A pose file round-trips; a mirror pose (orthonormal, det -1) is refused."""
    path = tmp_path / "intrinsics.txt"
    expected = Intrinsics(focal=100.0, cx=31.5, cy=15.5, height=32, width=64)
    path.write_text("100.0 31.5 15.5 0.\n0. 0. 0.\n1.\n32 64\n")
    assert srn_format.read_intrinsics(path) == expected
    path.write_text("100.0 31.5 15.5 0.\n0. 0. 0.\n0.\n1.\n32 64\n")
    assert srn_format.read_intrinsics(path) == expected
    srn_format.write_intrinsics(path, expected)
    assert path.read_text().splitlines()[-1] == "32 64" and srn_format.read_intrinsics(path) == expected
    pose = np.eye(4)
    pose[:3, 3] = [0.5, -1.0, 2.0]
    srn_format.write_pose(tmp_path / "pose.txt", pose)
    np.testing.assert_array_equal(srn_format.read_pose(tmp_path / "pose.txt"), pose.astype(np.float32))
    pose[0, 0] = -1.0
    srn_format.write_pose(tmp_path / "mirror.txt", pose)
    with pytest.raises(DepthnerfError, match="mirror.txt: pose is not a rigid transform"):
        srn_format.read_pose(tmp_path / "mirror.txt")


def test_text_files_saved_with_a_byte_order_mark_read_as_without(tmp_path: Path):
    """Windows editors start UTF-8 text with a byte-order mark; it is not part of the first number (intrinsics.txt
    was 'malformed intrinsics', a pose 'not 16 numbers')."""
    bom = "\ufeff"
    (tmp_path / "intrinsics.txt").write_text(bom + "100.0 31.5 15.5 0.\n0. 0. 0.\n1.\n32 64\n", encoding="utf-8")
    assert srn_format.read_intrinsics(tmp_path / "intrinsics.txt") == Intrinsics(focal=100.0, cx=31.5, cy=15.5,
                                                                                 height=32, width=64)
    srn_format.write_pose(tmp_path / "pose.txt", np.eye(4))
    (tmp_path / "pose.txt").write_text(bom + (tmp_path / "pose.txt").read_text(), encoding="utf-8")
    np.testing.assert_array_equal(srn_format.read_pose(tmp_path / "pose.txt"), np.eye(4, dtype=np.float32))
    (tmp_path / "depth_scale.txt").write_text(bom + "0.001\n", encoding="utf-8")
    assert srn_format.read_depth_scale(tmp_path / "depth_scale.txt") == 0.001


@pytest.mark.parametrize("case", sorted(BAD_INPUT_CASES))
def test_bad_input_raises_one_line_naming_the_file(tmp_path: Path, case: str):
    root = make_srn_fixture(tmp_path, with_depth=True, with_mask=True)
    split, path, text = BAD_INPUT_CASES[case](root)
    with pytest.raises(DepthnerfError) as err:
        srn.index_split(root, "cars", split)
    message = str(err.value)
    assert str(path) in message and text in message and "\n" not in message
    # Without the file checks, the same problem surfaces at the latest when the views are loaded.
    with pytest.raises(DepthnerfError) as err:
        for rec in srn.index_split(root, "cars", split, check_files=False).objects:
            srn.load_object(rec, with_depth=True, pixel_center=0.0)
    assert str(path) in str(err.value) and "\n" not in str(err.value)


def test_skip_bad_lists_what_it_skipped(tmp_path: Path):
    root = make_srn_fixture(tmp_path, splits={"train": 3})
    _, path, text = BAD_INPUT_CASES["pose_nan"](root)
    with pytest.raises(DepthnerfError):
        srn.index_split(root, "cars", "train")
    index = srn.index_split(root, "cars", "train", skip_bad=True)
    assert len(index.objects) == 2 and path.parents[1] not in [o.path for o in index.objects]
    assert len(index.skipped) == 1 and str(path) in index.skipped[0] and text in index.skipped[0]
    for obj in (root / "cars_train").iterdir():
        if obj != path.parents[1]:
            shutil.rmtree(obj)
    with pytest.raises(DepthnerfError, match=r"no usable objects \(1 skipped"):
        srn.index_split(root, "cars", "train", skip_bad=True)


def test_missing_split_folder(srn_root: Path):
    with pytest.raises(DepthnerfError, match=r"cars_val: split folder does not exist"):
        srn.index_split(srn_root, "cars", "val")
    with pytest.raises(DepthnerfError, match="unknown split"):
        srn.split_dir(srn_root, "cars", "training")


def test_synth_output_and_its_real_srn_spelling_load_identically(tmp_path: Path):
    from depthnerf.cli import main

    assert main(["synth", "--category", "cars", "--out", str(tmp_path / "synth"), "--train-objects", "1",
                 "--val-objects", "0", "--test-objects", "0", "--resolution", "16", "--views-train", "3",
                 "--quiet"]) == 0
    index = srn.index_split(tmp_path / "synth", "cars", "train")
    (rec,) = index.objects
    assert rec.num_views == 3 and rec.has_depth and rec.has_mask and rec.mesh_path is not None
    to_srn_style(rec.path, tmp_path / "srn" / "cars_train" / rec.object_id)
    a = srn.load_object(rec, with_depth=True, pixel_center=0.0)
    b = srn.load_object(srn.index_split(tmp_path / "srn", "cars", "train").objects[0], with_depth=True, pixel_center=0.0)
    assert a.intrinsics == b.intrinsics
    for name in ("images", "poses", "masks", "bboxes", "depths", "view_indices"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert a.masks.any() and (a.images < 1).any() and (a.images == 1).any()


@pytest.mark.parametrize("ray_distance", [False, True])
def test_backproject_inverts_projection(ray_distance: bool):
    """Back-projected pixels project back to their own pixel centres at the given z-depth / ray distance (to the
    float32 precision of the pixel directions)."""
    intr = Intrinsics(focal=30.0, cx=11.5, cy=7.5, height=16, width=24)
    c2w = look_at(torch.tensor([1.1, -0.7, 0.6])).double()
    gen = torch.Generator().manual_seed(3)
    depth = 0.5 + torch.rand(16, 24, generator=gen, dtype=torch.float64)
    keep = torch.rand(16, 24, generator=gen) > 0.3
    points = backproject(depth, c2w, intr, keep, ray_distance=ray_distance)
    cam = world_to_camera(points[None], c2w)[0]
    uv = project(cam[None], intr.focal, (intr.cx, intr.cy))[0]
    rows, cols = torch.nonzero(keep, as_tuple=True)
    assert torch.allclose(uv[:, 0], cols.double(), atol=1e-4) and torch.allclose(uv[:, 1], rows.double(), atol=1e-4)
    measured = cam.norm(dim=-1) if ray_distance else cam[:, 2]
    assert torch.allclose(measured, depth[keep], atol=1e-6)
