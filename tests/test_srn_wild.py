"""The SRN reader on data stored the way other people store it: accepted formats load the same tensors as the
documented ones, a bad optional part costs that part for that object only (a warning naming the file), and
``strict=True`` turns every such warning into a one-line error."""

from __future__ import annotations

import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from fixtures_srn import first_object, make_srn_fixture
from fixtures_wild import BAD_OPTIONAL_CASES, BLENDER_WORLD, to_third_party_style, write_depth_png16
from PIL import Image

from depthnerf.data import srn, srn_format
from depthnerf.errors import DataNote, DataWarning, DepthnerfError

PNG_SCALE = 1e-4


def _index(root: Path, **kw) -> tuple[srn.SplitIndex, list[warnings.WarningMessage]]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        index = srn.index_split(root, "cars", "train", **kw)
    return index, [w for w in caught if issubclass(w.category, DataWarning)]


def test_third_party_layout_reads_like_the_documented_one(tmp_path: Path):
    kw = {"splits": {"train": 4}, "with_depth": True, "with_mask": True, "with_mesh": True}
    original = srn.index_split(make_srn_fixture(tmp_path / "a", **kw), "cars", "train")
    root = to_third_party_style(make_srn_fixture(tmp_path / "b", **kw), PNG_SCALE)
    index, caught = _index(root)
    assert [w.category for w in caught] == [DataNote]  # no warning, one note about the extras
    note = str(caught[0].message)
    assert "meta.json (1), normal/ (1), render_log.txt (1)" in note and "\n" not in note
    recs = index.objects
    assert [r.depth_files[0] for r in recs] == ["000000.npy", "000000.png", "000000.npz", "000000.npz"]
    assert recs[1].depth_scale == PNG_SCALE and recs[0].depth_scale is None
    assert all(r.has_depth and r.has_mask and r.mesh_path is not None and not r.issues for r in recs)
    assert recs[0].ignored == ("meta.json", "normal/", "render_log.txt")
    for a_rec, b_rec in zip(original.objects, recs, strict=True):
        a = srn.load_object(a_rec, with_depth=True, pixel_center=0.0)
        b = srn.load_object(b_rec, with_depth=True, pixel_center=0.0)
        for name in ("images", "masks", "bboxes", "view_indices"):
            assert torch.equal(getattr(a, name), getattr(b, name)), name
        assert torch.allclose(b.poses.double(), torch.from_numpy(BLENDER_WORLD) @ a.poses.double(), atol=1e-6)
        assert torch.equal(b.depths > 0, a.depths > 0)
        assert (b.depths - a.depths).abs().max() <= PNG_SCALE / 2 * (1 + 1e-3)  # exact but for PNG rounding
    strict, caught = _index(root, strict=True)  # nothing irregular: strict reads it the same
    assert [r.depth_files for r in strict.objects] == [r.depth_files for r in recs]
    assert [w.category for w in caught] == [DataNote]


@pytest.mark.parametrize("case", sorted(BAD_OPTIONAL_CASES))
def test_bad_optional_part_is_off_for_that_object_only(tmp_path: Path, case: str):
    root = make_srn_fixture(tmp_path, splits={"train": 2}, with_depth=True, with_mask=True, with_mesh=True)
    part, mutate = BAD_OPTIONAL_CASES[case]
    path, text = mutate(root)
    index, caught = _index(root)
    assert len(caught) == 1 and caught[0].category is DataWarning
    message = str(caught[0].message)
    assert message.startswith(f"{path}: ") and text in message and "not used for this object" in message
    assert "\n" not in message
    bad, good = index.objects
    assert bad.path == first_object(root)
    usable = {"depth": bad.has_depth, "mask": bad.has_mask, "mesh": bad.mesh_path is not None}
    assert usable == {p: p != part for p in usable}
    assert good.has_depth and good.has_mask and good.mesh_path is not None and not good.issues
    views = srn.load_object(bad, pixel_center=0.0)  # the rest of the object still loads (masks fall back to the white rule)
    assert views.masks.any()
    with pytest.raises(DepthnerfError) as err:
        srn.index_split(root, "cars", "train", strict=True)
    assert str(path) in str(err.value) and text in str(err.value) and "\n" not in str(err.value)
    if part == "depth":  # without the file checks, a bad map is an error when it is loaded at the latest
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DataWarning)
            lazy = srn.index_split(root, "cars", "train", check_files=False).objects[0]
        if lazy.has_depth:
            with pytest.raises(DepthnerfError, match="depth"):
                srn.load_object(lazy, with_depth=True, pixel_center=0.0)


@pytest.mark.parametrize("case, body_problem", [("mesh_face_out_of_range", True), ("mesh_nan_vertex", True),
                                                ("mesh_truncated", False), ("mesh_not_ply", False)])
def test_training_checks_only_the_mesh_header(tmp_path: Path, case: str, body_problem: bool):
    """``mesh_body=False`` (training, which never uses mesh.ply) reads only the header: a bad body goes unreported
    and the mesh stays on, a bad header is still a warning; ``strict`` reads the body anyway."""
    root = make_srn_fixture(tmp_path, splits={"train": 2}, with_mesh=True)
    path, text = BAD_OPTIONAL_CASES[case][1](root)
    index, caught = _index(root, mesh_body=False)
    if body_problem:
        assert caught == [] and all(r.mesh_path is not None and not r.issues for r in index.objects)
    else:
        assert len(caught) == 1 and text in str(caught[0].message) and index.objects[0].mesh_path is None
    with pytest.raises(DepthnerfError, match=text):
        srn.index_split(root, "cars", "train", strict=True, mesh_body=False)


def test_equal_problems_of_a_split_are_one_warning(tmp_path: Path):
    root = make_srn_fixture(tmp_path, splits={"train": 3}, with_depth=True)
    for obj in sorted((root / "cars_train").iterdir()):
        for f in (obj / "depth").iterdir():
            write_depth_png16(f.with_suffix(".png"), srn_format.read_depth(f), PNG_SCALE)
            f.unlink()
    index, caught = _index(root)
    assert len(caught) == 1 and "needs a scale" in str(caught[0].message)
    assert "the same in 2 more objects" in str(caught[0].message)
    assert len(index.issues) == 3 and not any(o.has_depth for o in index.objects)
    (root / srn_format.DEPTH_SCALE_FILE).write_text(f"{PNG_SCALE}\n")  # at the dataset root
    index, caught = _index(root)
    assert caught == [] and all(o.has_depth and o.depth_scale == PNG_SCALE for o in index.objects)


def test_nearest_depth_scale_wins(tmp_path: Path):
    root = make_srn_fixture(tmp_path, splits={"train": 1}, with_depth=True)
    obj = first_object(root)
    truth = [srn_format.read_depth(f) for f in sorted((obj / "depth").iterdir())]
    for f, depth in zip(sorted((obj / "depth").iterdir()), truth, strict=True):
        write_depth_png16(f.with_suffix(".png"), depth, 2 * PNG_SCALE)
        f.unlink()
    (root / srn_format.DEPTH_SCALE_FILE).write_text("1.0\n")
    (root / "cars_train" / srn_format.DEPTH_SCALE_FILE).write_text(f"{PNG_SCALE}\n")
    (obj / srn_format.DEPTH_SCALE_FILE).write_text(f"{2 * PNG_SCALE}\n")
    rec = srn.index_split(root, "cars", "train").objects[0]
    assert rec.depth_scale == 2 * PNG_SCALE and rec.ignored == ()
    depths = srn.load_object(rec, with_depth=True, pixel_center=0.0).depths
    for got, want in zip(depths, truth, strict=True):
        assert np.abs(got.numpy() - want).max() <= PNG_SCALE * (1 + 1e-3)


def test_view_in_two_formats_uses_the_preferred_one(tmp_path: Path):
    root = make_srn_fixture(tmp_path, splits={"train": 1}, with_depth=True)
    obj = first_object(root)
    np.save(obj / "depth" / "000001.npy", np.full((16, 16), 9.0, np.float32))
    index, caught = _index(root)
    (rec,) = index.objects
    assert len(caught) == 1 and str(obj / "depth" / "000001.npy") in str(caught[0].message)
    assert "also has depth/000001.npz, which is used" in str(caught[0].message)
    assert rec.has_depth and rec.depth_files == ("000000.npz", "000001.npz", "000002.npz")
    assert srn.load_object(rec, [1], with_depth=True, pixel_center=0.0).depths.max() < 9.0
    with pytest.raises(DepthnerfError, match=r"000001\.npy: view 000001 also has"):
        srn.index_split(root, "cars", "train", strict=True)


def test_blank_view_may_have_all_zero_depth(tmp_path: Path):
    root = make_srn_fixture(tmp_path, splits={"train": 1}, with_depth=True)
    obj = first_object(root)
    srn_format.write_rgb(obj / "rgb" / "000002.png", np.ones((16, 16, 3), np.float32))
    srn_format.write_depth(obj / "depth" / "000002.npz", np.zeros((16, 16), np.float32))
    index, caught = _index(root, strict=True)
    assert caught == [] and index.objects[0].has_depth
    assert not srn.load_object(index.objects[0], with_depth=True, pixel_center=0.0).depths[2].any()
    srn_format.write_depth(obj / "depth" / "000001.npz", np.zeros((16, 16), np.float32))
    with pytest.raises(DepthnerfError, match=r"000001\.npz: depth map is all zero .* but rgb/000001\.png shows"):
        srn.load_object(srn.index_split(root, "cars", "train", check_files=False).objects[0], with_depth=True, pixel_center=0.0)


def test_read_depth_formats_and_shapes(tmp_path: Path):
    depth = np.where(np.arange(12).reshape(3, 4) % 3 == 0, 0.0, 1.0 + np.arange(12).reshape(3, 4) / 10)
    np.savez(tmp_path / "a.npz", depth=depth.astype(np.float32))
    np.save(tmp_path / "b.npy", depth[..., None].astype(np.float64))  # H x W x 1 is squeezed
    write_depth_png16(tmp_path / "c.png", depth, 1e-3)
    np.testing.assert_array_equal(srn_format.read_depth(tmp_path / "a.npz", shape=(3, 4)), depth.astype(np.float32))
    np.testing.assert_array_equal(srn_format.read_depth(tmp_path / "b.npy"), depth.astype(np.float32))
    np.testing.assert_allclose(srn_format.read_depth(tmp_path / "c.png", 1e-3), depth, atol=1e-6)
    with pytest.raises(DepthnerfError, match=r"c\.png: 16-bit PNG depth needs a scale.*depth_scale\.txt"):
        srn_format.read_depth(tmp_path / "c.png")
    Image.fromarray(np.zeros((3, 4), np.uint8) + 7).save(tmp_path / "d.png")
    with pytest.raises(DepthnerfError, match=r"d\.png: PNG depth must be 16-bit grey, got mode L"):
        srn_format.read_depth(tmp_path / "d.png", 1e-3)
    with pytest.raises(DepthnerfError, match=r"a\.npz: depth map has shape \(3, 4\), expected 4x3"):
        srn_format.read_depth(tmp_path / "a.npz", shape=(4, 3))
    np.save(tmp_path / "e.npy", np.array([{"depth": 1}], dtype=object))
    with pytest.raises(DepthnerfError, match=r"e\.npy: unreadable depth map"):  # never unpickled
        srn_format.read_depth(tmp_path / "e.npy")
    with pytest.raises(DepthnerfError, match=r"f\.exr: EXR depth is not supported"):
        srn_format.read_depth(tmp_path / "f.exr")


MASK = np.array([[0, 1, 1, 0], [1, 1, 0, 0], [0, 0, 0, 1]], dtype=bool)


@pytest.mark.parametrize("flavour", ["1", "L", "I;16", "LA", "RGB", "RGBA", "P"])
def test_masks_of_any_png_flavour(tmp_path: Path, flavour: str):
    m = MASK
    if flavour == "1":
        im = Image.fromarray(m)
    elif flavour == "L":
        im = Image.fromarray(np.where(m, 3, 0).astype(np.uint8))
    elif flavour == "I;16":
        im = Image.fromarray(np.where(m, 1000, 0).astype(np.uint16))
    elif flavour == "LA":  # object where grey is non-zero and opaque; a transparent grey pixel is background
        grey = np.where(m, 255, 0).astype(np.uint8)
        grey[0, 0] = 255
        im = Image.fromarray(np.stack([grey, np.where(m, 255, 0).astype(np.uint8)], -1))
    elif flavour == "RGB":  # any channel
        rgb = np.zeros(m.shape + (3,), np.uint8)
        rgb[..., 2] = np.where(m, 1, 0)
        im = Image.fromarray(rgb)
    elif flavour == "RGBA":  # white colour everywhere, alpha is the mask
        rgba = np.full(m.shape + (4,), 255, np.uint8)
        rgba[..., 3] = np.where(m, 255, 0)
        im = Image.fromarray(rgba)
    else:  # palette: index 1 is black, index 0 is red (a non-zero colour)
        im = Image.fromarray(np.where(m, 0, 1).astype(np.uint8))
        im.putpalette([255, 0, 0, 0, 0, 0])
    im.save(tmp_path / "m.png")
    assert Image.open(tmp_path / "m.png").mode.startswith(flavour)
    np.testing.assert_array_equal(srn_format.read_mask(tmp_path / "m.png"), m)


def test_extras_are_ignored_in_both_modes_but_rgb_stays_strict(tmp_path: Path):
    root = make_srn_fixture(tmp_path, splits={"train": 2}, with_depth=True)
    for obj in (root / "cars_train").iterdir():
        (obj / "render_log.txt").write_text("log\n")
    index, caught = _index(root, strict=True)
    assert [str(w.message).endswith("render_log.txt (2)") for w in caught] == [True]
    assert all(o.ignored == ("render_log.txt",) for o in index.objects)
    shutil.copy(first_object(root) / "render_log.txt", first_object(root) / "rgb" / "log.txt")
    with pytest.raises(DepthnerfError, match=r"rgb/log\.txt: unexpected entry in rgb/"):
        srn.index_split(root, "cars", "train")


def test_binary_ply_min_bytes_is_a_triangle_meshs_exact_size(tmp_path: Path):
    """For triangle meshes (every face a 3-list) the lower bound is the body's exact size; ASCII is not sized."""
    import trimesh

    from depthnerf.data.mesh_file import binary_ply_min_bytes

    for k, mesh in enumerate([trimesh.creation.box(), trimesh.creation.icosphere(1), trimesh.creation.cylinder(0.5, 1)]):
        mesh.visual.vertex_colors = [200, 10, 10, 255] if k == 1 else mesh.visual.vertex_colors  # uchar properties too
        data = trimesh.exchange.ply.export_ply(mesh, encoding="binary")
        end = data.index(b"end_header\n") + len(b"end_header\n")
        assert binary_ply_min_bytes(data[:end].split(b"end_header")[0].decode()) == len(data) - end
        ascii_header = trimesh.exchange.ply.export_ply(mesh, encoding="ascii").split(b"end_header")[0].decode()
        assert binary_ply_min_bytes(ascii_header) is None
