"""Bad or odd input to the inference commands (``reconstruct``, ``eval``, ``compare``, ``demo``, the app and the
Python API): each is one ``error:`` line naming the file or flag, found before any model loads, or read the way
the user sees it (no checkpoint is loaded here: every case fails or finishes before that)."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import torch
from PIL import Image

from depthnerf.app.messages import check_upload, one_line
from depthnerf.cli import main
from depthnerf.errors import DepthnerfError
from depthnerf.eval.config import ProtocolChoices, ProtocolConfig
from depthnerf.eval.shards import OBJECTS_DIR, SETTINGS_FILE, ObjectStore
from depthnerf.infer.session import SessionOptions
from depthnerf.reconstruct.photo import EXIF_ORIENTATION, MAX_SIDE, prepare_photo, read_photo


def one_error(capsys) -> str:
    """The single stderr line of a refused command."""
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err.strip()


def upright_photo() -> Image.Image:
    """A 32x48 (portrait) photo: white, with a red block in its upper left, so any turn or flip moves it."""
    rgb = np.full((48, 32, 3), 255, np.uint8)
    rgb[6:20, 4:14] = (200, 20, 20)
    return Image.fromarray(rgb)


def test_a_photo_with_an_exif_orientation_is_read_upright(tmp_path):
    """A camera's portrait photo stores landscape pixels and an EXIF orientation tag; viewers (and the user) see
    it turned. It is read as seen: the same input as the upright file, and a mask drawn on what the user sees fits."""
    upright = upright_photo()
    upright.save(tmp_path / "upright.png")
    tag = Image.Exif()
    tag[EXIF_ORIENTATION] = 6  # "turn 90 degrees clockwise to display": the pixels stored turned the other way
    upright.transpose(Image.Transpose.ROTATE_90).save(tmp_path / "camera.png", exif=tag.tobytes())
    mask = np.zeros((48, 32), np.uint8)
    mask[6:20, 4:14] = 255
    Image.fromarray(mask).save(tmp_path / "mask.png")
    seen = prepare_photo(tmp_path / "upright.png", None, 32)
    read = prepare_photo(tmp_path / "camera.png", None, 32)
    assert read.source_size == (48, 32)
    assert np.array_equal(read.mask, seen.mask) and np.allclose(read.image, seen.image)
    assert read.notes[0] == "image: turned upright by its EXIF orientation tag (6)"
    masked = prepare_photo(tmp_path / "camera.png", tmp_path / "mask.png", 32)  # was: "mask is 32x48 but ..."
    assert np.array_equal(masked.mask, seen.mask)


def test_a_very_long_photo_keeps_its_aspect_ratio_when_downscaled():
    """5000x80 px -> 1024x16 (its shape), not 1024x64 (the object stretched four times in height); 5000x20 would
    be 1024x4, below the 16 px a side needs, and is refused."""
    rgb = np.full((80, 5000, 3), 255, np.uint8)
    rgb[30:50, 1500:3500] = (200, 0, 0)
    notes: list[str] = []
    img, _, size = read_photo(Image.fromarray(rgb), notes)
    assert size == (80, 5000) and img.shape[:2] == (16, MAX_SIDE)
    assert notes == [f"downscaled from 5000x80 to {MAX_SIDE}x16 (box filter) first"]
    prepared = prepare_photo(Image.fromarray(rgb), None, 64, fill=0.5)
    rows = np.flatnonzero(prepared.mask.any(axis=1))
    assert rows.size <= 2  # a bar 100 times longer than thick stays a bar one or two pixels thick at 64 px
    with pytest.raises(DepthnerfError, match=r"^image: image is 5000x20 px, 1024x4 once downscaled to 1024 px"):
        read_photo(Image.fromarray(rgb[:20]), [])


@pytest.mark.parametrize("photo, mask, line", [
    ("missing.png", None, "{d}/missing.png: image file not found"),
    ("folder", None, "{d}/folder: is a folder, not an image file"),
    ("text.png", None, "{d}/text.png: unreadable image (cannot identify image file '{d}/text.png')"),
    ("tiny.png", None, "{d}/tiny.png: image is 1x1 px; at least 16 px per side are needed"),
    ("ok.png", "missing.png", "{d}/missing.png: mask file not found"),
    ("ok.png", "folder", "{d}/folder: is a folder, not a mask file"),
])
def test_reconstruct_refuses_a_bad_photo_or_mask_before_loading_the_model(tmp_path, capsys, photo, mask, line):
    """The checkpoint named does not exist: the photo's own error comes first, so no model (or Hub download)
    is waited for before a mistyped photo path is reported."""
    (tmp_path / "folder").mkdir()
    (tmp_path / "text.png").write_text("not an image\n")
    Image.new("RGB", (1, 1)).save(tmp_path / "tiny.png")
    upright_photo().save(tmp_path / "ok.png")
    argv = ["reconstruct", str(tmp_path / photo), "--checkpoint", "no-such-checkpoint", "--out", str(tmp_path / "o")]
    assert main(argv + (["--mask", str(tmp_path / mask)] if mask else [])) == 2
    assert one_error(capsys) == "error: " + line.format(d=tmp_path)
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("flags, line", [
    (["--views-stride", "0"], "--views-stride must be >= 1, got 0"),
    (["--max-objects", "0"], "--max-objects must be >= 1, got 0"),
    (["--resolution", "0"], "--resolution must be >= 8 (SSIM uniform7), got 0"),
    (["--resolution", "7"], "--resolution must be >= 8 (SSIM uniform7), got 7"),
    (["--ssim", "gaussian11", "--resolution", "10"], "--resolution must be >= 11 (SSIM gaussian11), got 10"),
    (["--mesh-resolution", "1"], "--mesh-resolution must be >= 2 and at most 1024 (up to 1024^3 density samples, 4.3 GB), got 1"),
    (["--mesh-resolution", "5000"], "--mesh-resolution must be >= 2 and at most 1024 (up to 1024^3 density samples, 4.3 GB), got 5000"),
    (["--no-mesh", "--mesh-resolution", "1"], "--mesh-resolution sets the mesh, which --no-mesh skips: pass one or the other"),
])
def test_eval_checks_its_protocol_flags_before_loading(tmp_path, capsys, flags, line):
    """Before: the checkpoint, the data and the prior cache were loaded first (a missing cache asked for a
    minutes-long ``depthnerf depth`` before the typo was named), and ``--resolution 0`` silently scored at the
    training resolution."""
    argv = ["eval", "--checkpoint", "no-such-checkpoint", "--data", str(tmp_path), "--out", str(tmp_path / "o")]
    assert main(argv + flags) == 2
    assert one_error(capsys) == f"error: {line}"
    with pytest.raises(DepthnerfError, match="--resolution must be >= 8"):
        ProtocolConfig(resolution=0)
    assert ProtocolConfig(resolution=11, choices=ProtocolChoices(ssim="gaussian11")).resolution == 11


def test_compare_and_resume_refuse_a_binary_json_file(tmp_path, capsys):
    """A summary.json or settings.json that is not UTF-8 text was a UnicodeDecodeError traceback."""
    summary = tmp_path / "summary.json"
    summary.write_bytes(b"\x00\xff\xfe binary")
    assert main(["compare", str(summary)]) == 2
    assert one_error(capsys) == f"error: {summary}: not a JSON text file (byte 1 is not UTF-8)"
    objects = tmp_path / "eval" / OBJECTS_DIR
    objects.mkdir(parents=True)
    (objects / "car0.json").write_text("{}")
    (objects / SETTINGS_FILE).write_bytes(b"\xff\xfe")
    with pytest.raises(DepthnerfError, match=f"{objects / SETTINGS_FILE}: unreadable .*; pass --overwrite"):
        ObjectStore(tmp_path / "eval", {"views_stride": 1}).prepare(overwrite=False)


@pytest.mark.parametrize("flags, line", [
    (["--seed", "-1"], "--seed must be >= 0 (a synthesis seed), got -1"),
    (["--out", "{d}/file"], "{d}/file: --out is a file, not a folder"),
    (["--out", "{d}/file/demo"], "{d}/file/demo: --out lies under {d}/file, which is a file, not a folder"),
    (["--views-stride", "0"], "--views-stride must be >= 1, got 0"),  # one line named all three flags
    (["--mesh-resolution", "1"], "--mesh-resolution must be >= 2 and at most 1024 (up to 1024^3 density samples, 4.3 GB), got 1"),
    (["--mesh-resolution", "5000"], "--mesh-resolution must be >= 2 and at most 1024 (up to 1024^3 density samples, 4.3 GB), got 5000"),
])
def test_demo_refuses_a_negative_seed_and_a_file_as_out(tmp_path, capsys, flags, line):
    """``--seed -1`` was numpy's ValueError traceback after both checkpoints loaded; ``--out FILE`` read
    "cannot create the output folder (File exists)"."""
    (tmp_path / "file").write_text("x")
    argv = ["demo", "--out", str(tmp_path / "demo"), "--cars-checkpoint", "no-such", "--chairs-checkpoint", "no-such"]
    assert main(argv + [f.format(d=tmp_path) for f in flags]) == 2
    assert one_error(capsys) == "error: " + line.format(d=tmp_path)


def test_python_api_device_mistakes_are_one_line():
    """``Reconstructor.from_pretrained(name, "gpu")`` (or "cuda" without a GPU) was torch's RuntimeError from deep
    inside the checkpoint loader."""
    with pytest.raises(DepthnerfError, match=r"^device gpu: choose cpu, cuda or cuda:N$"):
        SessionOptions(device="gpu")
    if not torch.cuda.is_available():
        with pytest.raises(DepthnerfError, match="^device cuda: no CUDA GPU is available to this process"):
            SessionOptions(device="cuda")
    assert SessionOptions(device="cpu").device == "cpu"


def test_app_names_a_folder_and_its_own_fields(tmp_path):
    """The page's words for every flag a reconstruction message names; a folder is not "file not found"."""
    (tmp_path / "folder").mkdir()
    with pytest.raises(DepthnerfError, match="^folder: is a folder, not an image file$"):
        check_upload(tmp_path / "folder")
    for flag, field in (("--elevation", "the elevation"), ("--facing", "the object facing")):
        line = one_line(DepthnerfError(f"{flag} must be within ..., got nan"), None)
        assert line == f"error: {field} must be within ..., got nan"



def test_eval_refuses_a_file_as_out_before_loading(tmp_path, capsys):
    """``--out FILE`` was a FileExistsError traceback, after the checkpoint and the data had loaded."""
    (tmp_path / "file").write_text("x")
    argv = ["eval", "--checkpoint", "no-such-checkpoint", "--data", str(tmp_path)]
    assert main(argv + ["--out", str(tmp_path / "file")]) == 2
    assert one_error(capsys) == f"error: {tmp_path / 'file'}: --out is a file, not a folder"
    assert main(argv + ["--out", str(tmp_path / "file" / "eval")]) == 2
    assert one_error(capsys) == (f"error: {tmp_path / 'file' / 'eval'}: --out lies under "
                                 f"{tmp_path / 'file'}, which is a file, not a folder")
    run = ["eval", "--data", str(tmp_path), "--run"]  # was "afile/eval/test: the output folder's parent ..."
    assert main(run + [str(tmp_path / "file")]) == 2
    assert one_error(capsys) == f"error: {tmp_path / 'file'}: --run needs a training run folder, this is a file"
    assert main(run + [str(tmp_path / "none")]) == 2
    assert one_error(capsys) == f"error: {tmp_path / 'none'}: --run needs a training run folder, no such folder"


@pytest.mark.skipif(importlib.util.find_spec("gradio") is None, reason="needs the [app] extra")
@pytest.mark.parametrize("flags, line", [
    (["--device", "gpu"], "--device gpu: choose auto, cpu, cuda or cuda:N"),
    (["--work-dir", "{d}/file"], "{d}/file: --work-dir is a file, not a folder"),
    (["--work-dir", "{d}/file/runs"], "{d}/file/runs: --work-dir lies under {d}/file, which is a file, not a folder"),
])
def test_app_refuses_a_bad_device_or_work_dir_before_serving(tmp_path, capsys, flags, line):
    """Both were tracebacks: the device one from the first model's ``.to("gpu")``, the other from ``mkdir``."""
    (tmp_path / "file").write_text("x")
    assert main(["app", "--port", "7987", *(f.format(d=tmp_path) for f in flags)]) == 2
    assert one_error(capsys) == "error: " + line.format(d=tmp_path)
