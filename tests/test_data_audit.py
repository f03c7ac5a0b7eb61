"""Mistakes a user makes with SRN-format data, each found by the audit of the data reader: every one is one line
naming the file (or the folder) and the problem, or a warning costing only the optional part, never a traceback,
a silent wrong value or a silently reused stale prior."""

from __future__ import annotations

import io
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from fixtures_srn import first_object, make_srn_fixture, write_png16
from PIL import Image

from depthnerf.cli import main
from depthnerf.data import srn_format
from depthnerf.data.srn import index_split, load_object
from depthnerf.data.view_store import ViewStore
from depthnerf.depth.bundled import BundledDepthNet, BundledNetConfig, save_bundled
from depthnerf.depth.cache import PriorStore, rgb_fingerprint
from depthnerf.errors import DataWarning, DepthnerfError

INTRINSICS = "8.2 8. 8. 0.\n0. 0. 0.\n1.\n{}\n"


@pytest.mark.parametrize(("content", "problem"), [
    (b"\xe3\x81\x00\xff binary", "malformed intrinsics (not a text file)"),
    (INTRINSICS.format("16.5 16").encode(), "image size '16.5 16' on the last line is not two whole numbers 'H W'"),
    (INTRINSICS.format("nan 16").encode(), "image size 'nan 16' on the last line is not two whole numbers 'H W'"),
    (b"8.2 1e9 8. 0.\n0. 0. 0.\n1.\n16 16\n", "principal point (1e+09, 8) lies outside the 16x16 image"),
    (b"8.2 8. -0.5 0.\n0. 0. 0.\n1.\n16 16\n", "principal point (8, -0.5) lies outside the 16x16 image"),
])
def test_bad_intrinsics_are_one_line(tmp_path: Path, content: bytes, problem: str, capsys):
    root = make_srn_fixture(tmp_path, splits={"train": 1})
    path = first_object(root) / "intrinsics.txt"
    path.write_bytes(content)
    with pytest.raises(DepthnerfError, match=re.escape(problem)):
        srn_format.read_intrinsics(path)
    assert main(["inspect", "--data", str(root)]) == 2
    assert capsys.readouterr().err.strip() == f"error: {path}: {problem}"
    path.write_text(INTRINSICS.format("16. 16"))  # a whole number written as a float is still one
    assert srn_format.read_intrinsics(path).height == 16


def test_data_one_or_two_levels_too_deep_names_the_root(tmp_path: Path, capsys):
    root = make_srn_fixture(tmp_path / "srn", category="chairs", splits={"train": 1, "test": 1})
    nested = root / "chairs_train" / "chairs_2.0_train"
    for data, level in ((root / "chairs_train", "a split"), (nested, "a split"), (root / "chairs_test", "a split"),
                        (next(nested.iterdir()), "an object")):
        expected = f"error: {data}: is {level} folder, not a dataset root; "
        assert main(["inspect", "--data", str(data)]) == 2
        err = capsys.readouterr().err
        assert err.startswith(expected) and err.rstrip().endswith(f"(here probably {root})"), err
        assert main(["depth", "--data", str(data), "--depth", "bundled", "--no-progress"]) == 2
        assert capsys.readouterr().err.startswith(expected)
        with pytest.raises(DepthnerfError, match="folder, not a dataset root"):  # what train and eval call
            index_split(data, "chairs", "train")
    assert not (root / "chairs_train" / "depth_priors").exists()  # no cache written into the split folder
    with pytest.raises(DepthnerfError, match="dataset folder does not exist"):
        index_split(tmp_path / "nowhere", "cars", "train")


def test_depth_priors_are_made_when_an_optional_mask_is_bad(tmp_path: Path, capsys):
    root = make_srn_fixture(tmp_path / "srn", splits={"train": 1}, views=2, with_mask=True)
    bad = first_object(root) / "mask" / "000001.png"
    bad.write_bytes(bad.read_bytes()[:60])  # truncated: train and inspect go on without mask/, with a warning
    torch.manual_seed(0)
    weights = tmp_path / "w.safetensors"
    save_bundled(BundledDepthNet(BundledNetConfig(widths=(4, 6, 8), input_size=16)), weights)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DataWarning)
        assert main(["depth", "--data", str(root), "--depth", "bundled", "--depth-checkpoint", str(weights),
                     "--no-progress"]) == 0
        records = index_split(root, "cars", "train").objects
    assert "1 objects computed" in capsys.readouterr().out
    PriorStore.open(root, "bundled", str(weights), resolution=16).check(records)


def test_oracle_prior_names_why_depth_is_unusable(tmp_path: Path):
    root = make_srn_fixture(tmp_path, splits={"train": 1}, with_depth=True)
    bad = first_object(root) / "depth" / "000001.npz"
    srn_format.write_depth(bad, np.full((16, 16), np.nan, dtype=np.float32))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DataWarning)
        records = index_split(root, "cars", "train").objects
    store = PriorStore.open(root, "oracle", resolution=16)
    with pytest.raises(DepthnerfError) as err:
        store.check(records)
    assert str(err.value) == (f"{first_object(root)}: the 'oracle' prior needs ground-truth depth/ maps, its depth/ "
                              f"is not usable ({bad}: depth map holds NaN or inf (256 of 256 pixels))")
    with pytest.raises(DepthnerfError, match="needs ground-truth depth/ maps, none found"):
        PriorStore.open(root, "oracle", resolution=16).check(
            index_split(make_srn_fixture(tmp_path / "b", splits={"train": 1}), "cars", "train").objects)


def test_a_jpeg_mask_is_refused_not_read_as_a_wider_mask(tmp_path: Path):
    root = make_srn_fixture(tmp_path, splits={"train": 1}, with_mask=True)
    path = first_object(root) / "mask" / "000001.png"
    buffer = io.BytesIO()
    Image.open(path).save(buffer, "JPEG", quality=75)  # ringing makes black background pixels non-zero
    path.write_bytes(buffer.getvalue())
    problem = f"{path}: mask is a JPEG file, not a PNG"
    with pytest.raises(DepthnerfError, match="mask is a JPEG file, not a PNG"):
        srn_format.read_mask(path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        record = index_split(root, "cars", "train").objects[0]
    assert not record.has_mask and [str(w.message).split(" (")[0] for w in caught] == [problem]
    with pytest.raises(DepthnerfError, match="mask is a JPEG file"):
        index_split(root, "cars", "train", strict=True)


def test_an_empty_image_file_is_one_plain_line(tmp_path: Path, capsys):
    root = make_srn_fixture(tmp_path, splits={"train": 1})
    path = first_object(root) / "rgb" / "000001.png"
    path.write_bytes(b"")
    expected = f"{path}: unreadable image (not an image: the file is empty or of a format Pillow does not know)"
    assert main(["inspect", "--data", str(root)]) == 2
    assert capsys.readouterr().err.strip() == f"error: {expected}"
    record = index_split(root, "cars", "train", check_files=False).objects[0]
    with pytest.raises(DepthnerfError) as err:
        load_object(record, pixel_center=0.0)
    assert str(err.value) == expected


def test_a_view_store_inside_a_split_folder_is_refused(tmp_path: Path):
    root = make_srn_fixture(tmp_path, splits={"train": 1})
    records = index_split(root, "cars", "train").objects
    for folder in (root / "cars_train" / "store", first_object(root) / "store"):
        with pytest.raises(DepthnerfError, match="inside the split folder .* read as an object"):
            ViewStore(folder, 16, 0.0).ensure(records)
        assert not folder.exists()
    assert ViewStore(root / "store", 16, 0.0).ensure(records)["built"] == 1  # beside the splits: fine
    assert [r.object_id for r in index_split(root, "cars", "train").objects] == [records[0].object_id]


def test_a_prior_goes_stale_when_an_image_changes_but_keeps_its_size(tmp_path: Path):
    root = make_srn_fixture(tmp_path, splits={"train": 1})
    obj = first_object(root)
    for path in (obj / "rgb").iterdir():  # uncompressed PNGs: the file size depends on the image size only
        Image.open(path).save(path, compress_level=0)
    record = index_split(root, "cars", "train").objects[0]
    before = rgb_fingerprint(record)
    path = obj / "rgb" / "000001.png"
    size = path.stat().st_size
    Image.open(path).rotate(90).save(path, compress_level=0)
    assert path.stat().st_size == size and rgb_fingerprint(record) != before


def test_a_cache_made_with_the_earlier_fingerprint_is_checked_as_it_was_made(tmp_path):
    """Caches written before the byte-wise fingerprint (view names, RGB sizes, the first file's bytes) are kept, not
    recomputed, and still go stale when an image changes size; new entries carry the ``rgb-bytes:`` scheme."""
    from depthnerf.depth.cache import _sizes_fingerprint, fingerprint_matches

    root = make_srn_fixture(tmp_path / "d", "cars", {"train": 1}, views=3, size=16)
    record = index_split(root, "cars", "train").objects[0]
    legacy, current = _sizes_fingerprint(record), rgb_fingerprint(record)
    assert current.startswith("rgb-bytes:") and fingerprint_matches(current, record)
    assert fingerprint_matches(legacy, record) and not fingerprint_matches(None, record)
    path = Path(record.rgb_path(1))
    Image.new("RGB", (16, 16), (10, 200, 30)).save(path, compress_level=9)  # another size
    assert not fingerprint_matches(legacy, record) and not fingerprint_matches(current, record)


def test_jpeg_rgb_under_a_png_name_is_read_with_one_warning_per_split(tmp_path: Path, capsys):
    """JPEG bytes in ``rgb/*.png`` of two objects: read as the JPEG Pillow decodes, one warning for the split that
    names the first file and counts both; ``strict`` refuses it."""
    from depthnerf.data.validate import summarize_split

    root = make_srn_fixture(tmp_path, splits={"train": 2}, views=3)
    folder = root / "cars_train"
    objects = sorted(p for p in folder.iterdir() if p.is_dir())
    paths = [objects[0] / "rgb" / "000001.png", objects[1] / "rgb" / "000002.png"]
    for path in paths:
        buffer = io.BytesIO()
        Image.open(path).convert("RGB").save(buffer, "JPEG", quality=75)
        path.write_bytes(buffer.getvalue())
    expected = f"{folder}: 2 rgb files hold JPEG data under a .png name (first: {paths[0]}); read as JPEG (lossy)"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        index = index_split(root, "cars", "train")
    assert [(w.category, str(w.message)) for w in caught] == [(DataWarning, expected)]
    assert summarize_split(index).warnings == [expected]
    for record, path in zip(index.objects, paths, strict=True):
        with Image.open(path) as im:
            assert im.format == "JPEG"
            pil = np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0
        views = load_object(record, [record.view_names.index(path.stem)], pixel_center=0.0)
        assert np.array_equal(views.images[0].permute(1, 2, 0).numpy(), pil)
    with pytest.raises(DepthnerfError, match=re.escape(f"{paths[0]}: image holds JPEG data under a .png name")):
        index_split(root, "cars", "train", strict=True)
    assert main(["inspect", "--data", str(root)]) == 0
    assert capsys.readouterr().err.strip() == f"warning: {expected}"


def test_a_data_warning_is_printed_by_rank_zero_alone(tmp_path: Path, capsys, monkeypatch):
    """In a torchrun job every rank indexes the same splits: rank 0 prints the split's warning, rank 1 does not
    (its exit status is the same)."""
    root = make_srn_fixture(tmp_path, splits={"train": 1}, views=3)
    path = next(p for p in (root / "cars_train").iterdir() if p.is_dir()) / "rgb" / "000001.png"
    buffer = io.BytesIO()
    Image.open(path).convert("RGB").save(buffer, "JPEG", quality=75)
    path.write_bytes(buffer.getvalue())
    monkeypatch.setenv("WORLD_SIZE", "2")
    for rank, lines in (("0", 1), ("1", 0)):
        monkeypatch.setenv("RANK", rank)
        assert main(["inspect", "--data", str(root)]) == 0
        err = capsys.readouterr().err
        assert err.count("warning: ") == lines and err.count("JPEG data under a .png name") == lines, (rank, err)


def test_a_legacy_prior_entry_is_checked_without_hashing_every_image(tmp_path: Path, monkeypatch):
    """``depthnerf depth`` (and the store's check) compute the byte-wise fingerprint for ``rgb-bytes:`` entries
    and for entries they write, never to check an entry of the earlier scheme."""
    from safetensors.torch import load_file

    from depthnerf.depth import cache, precompute
    from depthnerf.depth.precompute import PrecomputeConfig, precompute_priors

    root = make_srn_fixture(tmp_path / "d", "cars", {"train": 2}, views=3, size=16)
    torch.manual_seed(0)
    weights = tmp_path / "w.safetensors"
    save_bundled(BundledDepthNet(BundledNetConfig(widths=(4, 6, 8), input_size=16)), weights)
    cfg = PrecomputeConfig(data_root=root, estimator="bundled", checkpoint=str(weights), splits=("train",),
                           progress=False)
    summary = precompute_priors(cfg)
    assert summary.computed == 2
    records = index_split(root, "cars", "train").objects
    legacy, current = records
    path = cache.object_path(summary.cache_dir, legacy)
    meta = cache.read_object_metadata(path)
    cache.write_object_priors(path, load_file(str(path))["disparity"],
                              {**meta, "fingerprint": cache._sizes_fingerprint(legacy)})
    hashed = []
    real = cache.rgb_fingerprint

    def counting(record):
        hashed.append(record.object_id)
        return real(record)

    monkeypatch.setattr(cache, "rgb_fingerprint", counting)
    monkeypatch.setattr(precompute, "rgb_fingerprint", counting)
    summary = precompute_priors(cfg)
    assert (summary.computed, summary.skipped, hashed) == (0, 2, [current.object_id])
    hashed.clear()
    PriorStore.open(root, "bundled", str(weights), resolution=16).check(records)
    assert hashed == [current.object_id]
    hashed.clear()
    Image.new("RGB", (16, 16), (10, 200, 30)).save(legacy.rgb_path(1), compress_level=9)  # the legacy entry is stale
    summary = precompute_priors(cfg)
    assert (summary.computed, summary.stale, summary.skipped) == (1, 1, 1)
    assert hashed == [legacy.object_id, current.object_id]  # rewritten in the byte-wise scheme
    assert cache.read_object_metadata(path)["fingerprint"] == real(legacy)


def test_eight_bit_values_in_a_16_bit_colour_png_are_refused_not_read_as_blank(tmp_path: Path, capsys):
    """Pillow reads 16-bit colour by its high bytes: 8-bit values stored in 16 bits would read as a black image
    (RGB) or a blank one (RGBA, alpha 0); full-range 16-bit values (v * 257) read as their 8-bit selves."""
    root = make_srn_fixture(tmp_path, splits={"train": 1}, with_mask=True)
    path = first_object(root) / "rgb" / "000001.png"
    rgb8 = np.round(srn_format.read_rgb(path) * 255).astype(np.uint16)
    for layout in (rgb8, np.concatenate([rgb8, np.full_like(rgb8[..., :1], 255)], axis=-1)):
        write_png16(path, layout * 257)
        assert np.array_equal(np.round(srn_format.read_rgb(path) * 255), rgb8)
        write_png16(path, layout)
        with pytest.raises(DepthnerfError, match="16-bit colour PNG whose values all lie below 256"):
            srn_format.read_rgb(path)
    assert main(["inspect", "--data", str(root)]) == 2  # a required file: an error in inspect too
    assert "16-bit colour PNG whose values all lie below 256" in capsys.readouterr().err


def test_an_all_background_mask_of_a_view_that_shows_an_object_is_refused(tmp_path: Path):
    root = make_srn_fixture(tmp_path, splits={"train": 1}, with_mask=True)
    obj = first_object(root)
    record = index_split(root, "cars", "train").objects[0]
    mask = srn_format.read_mask(obj / "mask" / "000001.png")
    assert mask.any() and not mask.all()
    srn_format.write_mask(obj / "mask" / "000001.png", np.zeros_like(mask))
    with pytest.raises(DepthnerfError, match=r"000001.png: mask is all background but rgb/000001.png shows an "
                                             r"object on a white background"):
        load_object(record, pixel_center=0.0)
    srn_format.write_rgb(obj / "rgb" / "000001.png", np.ones(mask.shape + (3,)))  # an empty view: a valid mask
    assert not load_object(record, views=[1], pixel_center=0.0).masks.any()
    srn_format.write_rgb(obj / "rgb" / "000001.png", np.zeros(mask.shape + (3,)))  # no white: the mask is believed
    assert not load_object(record, views=[1], pixel_center=0.0).masks.any()
    write_png16(obj / "mask" / "000002.png", np.repeat(mask[..., None], 3, -1).astype(np.uint16) * 255)
    with warnings.catch_warnings(record=True) as caught:  # a 16-bit colour mask is decoded by inspect: lenient...
        warnings.simplefilter("always")
        assert not index_split(root, "cars", "train").objects[0].has_mask
    assert any("000002.png: mask is all background" in str(w.message) for w in caught)
    with pytest.raises(DepthnerfError, match="000002.png: mask is all background"):  # ... or strict
        index_split(root, "cars", "train", strict=True)


def test_in_dataset_is_the_root_and_its_split_folders_only(tmp_path):
    from depthnerf.data.records import in_dataset

    root = tmp_path / "data"
    (root / "cars_test").mkdir(parents=True)
    inside = [root, root / "cars_test", root / "cars_test" / "x" / "y", root / "cars_val", root / "chairs_train" / "r"]
    beside = [root / "runs", root / "runs" / "cars_test", root / "depth_priors", tmp_path, tmp_path / "cars_test"]
    assert [in_dataset(p, root) for p in inside] == [True] * len(inside)
    assert [in_dataset(p, root) for p in beside] == [False] * len(beside)
    assert in_dataset(root / ".." / "data" / "cars_test", root)  # resolved
