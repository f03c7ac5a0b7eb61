"""``depthnerf app`` without a browser: the plain functions of :mod:`depthnerf.app.logic` (upload checks, one-line
messages for every kind of bad input, a real run through the shipped checkpoint and the files it collects), the
command (install hint without gradio, bind address, queue) and the promise that the core never imports gradio."""

from __future__ import annotations

import importlib.util
import json
import socket
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image

from depthnerf.app.logic import (
    AppConfig,
    AppSession,
    RunRequest,
    check_upload,
    examples,
    one_line,
    resolve_model,
)
from depthnerf.cli import main
from depthnerf.data.synth.framing import get_framing
from depthnerf.errors import DepthnerfError

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> AppSession:
    return AppSession(AppConfig(mesh_resolution=24, work_dir=tmp_path_factory.mktemp("app"), keep_runs=2))


def _write(path: Path, im: Image.Image, **kw) -> Path:
    im.save(path, **kw)
    return path


def bad_inputs(tmp: Path) -> dict[str, tuple[Path | None, str]]:
    """name -> (file, expected text of the one-line message)."""
    (tmp / "notes.png").write_text("these are notes, not pixels\n")
    car = Image.open(examples()[0]).convert("RGB")
    whole = tmp / "whole.png"
    car.save(whole)
    (tmp / "truncated.png").write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    rng = np.random.default_rng(0)
    noise = rng.integers(0, 256, (120, 160, 3), dtype=np.uint8)
    noise[40:80, 50:110] = (200, 30, 30)
    return {
        "non-image": (tmp / "notes.png", "error: notes.png: not an image (cannot identify image file"),
        "truncated": (tmp / "truncated.png", "error: truncated.png: unreadable image"),
        "1x1": (_write(tmp / "dot.png", Image.new("RGB", (1, 1), (9, 9, 9))),
                "error: dot.png: image is 1x1 px; at least 16 px per side are needed"),
        "no foreground": (_write(tmp / "blank.png", Image.new("RGB", (64, 48), (250, 250, 250))),
                          "error: blank.png: no object found (the mask is empty)"),
        "cluttered": (_write(tmp / "scene.jpg", Image.fromarray(noise), quality=95),
                      "error: scene.jpg: the background is not a plain colour"),
        "gif": (_write(tmp / "anim.gif", car), "error: anim.gif: GIF images are not supported; use a PNG, JPEG or WebP photo"),
        "nothing": (None, "error: no image: upload a PNG, JPEG or WebP photo, or pick an example"),
    }


def png16(path: Path, pixels: np.ndarray) -> Path:
    """A 16-bit PNG (grey, grey+alpha, RGB or RGBA by the channel count), written by hand: Pillow cannot."""
    h, w, c = pixels.shape
    raw = b"".join(b"\x00" + pixels[y].astype(">u2").tobytes() for y in range(h))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", w, h, 16, {1: 0, 2: 4, 3: 2, 4: 6}[c], 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw))
                     + chunk(b"IEND", b""))
    return path


def accepted_inputs(tmp: Path) -> dict[str, tuple[Path, str]]:
    """Odd but usable images: name -> (file, a note the preview must show)."""
    car = Image.open(examples()[0])
    rgb = Image.new("RGB", car.size, (255, 255, 255))
    rgb.paste(car, mask=car.getchannel("A"))
    big = Image.new("RGB", (6000, 4000), (255, 255, 255))
    big.paste(rgb.resize((2400, 2400)), (1800, 800))
    grey = np.asarray(rgb.convert("L"), dtype=np.uint16) * 257
    return {
        "6000x4000": (_write(tmp / "big.png", big, compress_level=1),
                      "downscaled from 6000x4000 to 1024x683 (box filter) first"),
        "grayscale": (_write(tmp / "grey.jpg", rgb.convert("L")), "grayscale image: replicated to RGB"),
        "16-bit": (_write(tmp / "grey16.png", Image.fromarray(grey)), "grayscale image: replicated to RGB"),
        "rgba webp": (_write(tmp / "car.webp", car, lossless=True), "mask: alpha > 0.5"),
        "16-bit rgb": (png16(tmp / "rgb16.png", np.asarray(rgb, dtype=np.uint16) * 257),
                       "mask: pixels differing from the border colour [255, 255, 255]"),
        "16-bit rgba": (png16(tmp / "rgba16.png", np.asarray(car, dtype=np.uint16) * 257), "mask: alpha > 0.5"),
    }


def test_every_bad_input_is_one_line_and_the_session_keeps_working(session, tmp_path):
    for kind, (path, text) in bad_inputs(tmp_path).items():
        for message in (session.run(RunRequest(path, "car", views=1)).message,
                        session.preview(RunRequest(path, "car"))[1]):
            assert message.startswith(text), (kind, message)
            assert "\n" not in message and "Traceback" not in message and str(tmp_path) not in message, kind
    for kind, (path, note) in accepted_inputs(tmp_path).items():
        image, message = session.preview(RunRequest(path, "car"))
        assert message.startswith(f"ready: {path.name}") and note in message, (kind, message)
        assert image.shape == (64, 64, 3) and image.dtype == np.uint8


def test_request_checks(session, tmp_path):
    example = examples()[0]
    assert session.run(RunRequest(example, "car", views=0)).message == "error: orbit views must be within 1..36, got 0"
    assert session.run(RunRequest(example, "car", foreground_ratio=1.5)).message.startswith(
        "error: foreground ratio must be within 0.05..1")
    out = session.run(RunRequest(example, "car", depth_prior="midas"))
    assert out.message.startswith("error: depth prior must be one of bundled, depth-anything-v2") and not out.ok
    out = session.run(RunRequest(example, "car", depth_prior="depth-anything-v2",
                                 depth_checkpoint=str(tmp_path / "no-da-weights")))
    assert out.message.startswith("error: ") and "no-da-weights" in out.message and "\n" not in out.message
    out = session.run(RunRequest(example, "car", checkpoint_path=str(tmp_path / "nope.safetensors")))
    assert out.message.startswith("error: ") and "nope.safetensors" in out.message and "\n" not in out.message


def test_resolve_model_and_messages(tmp_path):
    assert resolve_model(RunRequest(None, "car")) == "cpu-cars-depth"
    assert resolve_model(RunRequest(None, "chair")) == "cpu-chairs-depth"
    assert resolve_model(RunRequest(None, "car", checkpoint_path=" runs/x ")) == "runs/x"
    assert one_line(DepthnerfError("/tmp/gradio/ab/c.png: bad\nthing"), "/tmp/gradio/ab/c.png") == "error: c.png: bad thing"
    assert one_line(KeyError("k"), None) == "internal error (KeyError): 'k'"
    with pytest.raises(DepthnerfError, match="missing.png: file not found"):
        check_upload(tmp_path / "missing.png")


def test_a_run_collects_every_output(session):
    calls = []
    out = session.run(RunRequest(examples()[0], "car", foreground_ratio=0.5, elevation=25, views=2),
                      progress=lambda frac, text: calls.append((frac, text)))
    assert out.ok and out.message.startswith("done in ") and "2 views" in out.message, out.message
    run = out.input_image.parent
    manifest = json.loads((run / "manifest.json").read_text())
    assert manifest["settings"]["fill"] == 0.5 and manifest["settings"]["elevation"] == 25
    assert manifest["settings"]["depth_estimator"] == "bundled" and Path(manifest["checkpoint"]).name == \
        "cpu-cars-depth.safetensors"
    mask = np.asarray(Image.open(out.input_mask)) > 0  # foreground ratio = fill: the longer box side is half the frame
    rows, cols = np.where(mask.any(1))[0], np.where(mask.any(0))[0]
    assert abs(max(rows[-1] - rows[0], cols[-1] - cols[0]) + 1 - 32) <= 2
    assert out.depth_prior.name == "depth_prior.png" and out.gif.name == "turntable.gif"
    assert [p.name for p in out.downloads] == ["mesh.glb", "mesh.ply", "points.ply"]
    assert all(p.is_file() and p.stat().st_size > 0 for p in [*out.downloads, out.gif, out.depth_prior])
    if importlib.util.find_spec("imageio_ffmpeg") is not None:
        assert out.video.name == "turntable.mp4" and out.video.read_bytes()[4:8] == b"ftyp"
    assert out.viewer_glb is not None and out.viewer_glb.name == "mesh.glb"
    ply, glb = trimesh.load(run / "mesh.ply", force="mesh"), trimesh.load(out.viewer_glb, force="mesh")
    x, y, z = np.asarray(ply.vertices, np.float64).T  # the viewer's GLB is glTF's +y up: (x, y, z) -> (x, z, -y)
    assert len(ply.vertices) > 0 and np.allclose(np.sort(np.asarray(glb.vertices), 0),
                                                 np.sort(np.stack([x, z, -y], 1), 0), atol=1e-5)
    assert "fill 0.50" in out.details and "depth prior **bundled**" in out.details
    assert calls[0][0] == 0.0 and [t for _, t in calls][-1] == "writing outputs"
    # keep_runs=2: older run folders are deleted as new ones come
    for _ in range(2):
        session.run(RunRequest(examples()[0], "car", views=1))
    assert len(list(session.work_dir.glob("run-*"))) == 2 and not run.exists()
    later = AppSession(AppConfig(work_dir=session.work_dir))  # a reused work folder: new runs, never old names
    assert later._new_run_dir().name > max(d.name for d in session.work_dir.glob("run-*"))


def test_training_fill_is_the_checkpoints(session):
    """The shipped checkpoints were trained on SRN-framed data: the page's default is that framing's fill."""
    assert session.training_fill("car") == pytest.approx(get_framing("srn").fill("cars", 0.0))
    assert session.training_fill("chair") == pytest.approx(get_framing("srn").fill("chairs", 0.0))
    assert session.training_fill("chair") < session.training_fill("car")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_core_never_imports_gradio():
    code = ("import sys, depthnerf.cli, depthnerf.app.logic, depthnerf.commands.app, depthnerf.reconstruct.reconstructor;"
            "print('gradio' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout.strip() == "False"


def test_app_command_without_gradio_prints_the_install_hint(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "gradio", None)  # find_spec -> None, as when it is not installed
    assert main(["app"]) == 2
    err = capsys.readouterr().err
    assert err == "error: depthnerf app needs gradio, which is not installed: pip install -e \".[app]\" " \
                  "(or 'depthnerf[app]')\n"
    assert "app" in subprocess.run([sys.executable, "-m", "depthnerf", "--help"], capture_output=True, text=True,
                                   cwd=ROOT).stdout


def test_app_command_binds_localhost_without_share_and_queues_one_at_a_time(monkeypatch, tmp_path):
    gr = pytest.importorskip("gradio", reason="gradio is not installed (pip install -e '.[app]')")
    seen = {}

    def fake_launch(self, **kwargs):
        seen.update(kwargs, page=self)

    monkeypatch.setattr(gr.Blocks, "launch", fake_launch)
    port = free_port()  # the command checks that the port is free before it builds the page
    assert main(["app", "--port", str(port), "--views", "2", "--work-dir", str(tmp_path)]) == 0
    assert seen["server_name"] == "127.0.0.1" and seen["server_port"] == port and seen["share"] is False
    assert seen["page"]._queue.default_concurrency_limit == 1 and seen["prevent_thread_lock"] is True
    assert main(["app", "--share", "--host", "0.0.0.0", "--port", str(port), "--work-dir", str(tmp_path)]) == 0
    assert seen["share"] is True and seen["server_name"] == "0.0.0.0"
    assert main(["app", "--views", "40"]) == 2


def test_a_busy_port_is_one_line(monkeypatch, tmp_path, capsys):
    gr = pytest.importorskip("gradio", reason="gradio is not installed (pip install -e '.[app]')")

    def busy(self, **kwargs):
        raise OSError("Cannot find empty port in range: 7998-7998. You can specify a different port ...")

    monkeypatch.setattr(gr.Blocks, "launch", busy)
    port = free_port()  # free when checked, taken when the server binds it (e.g. by another process meanwhile)
    assert main(["app", "--port", str(port), "--work-dir", str(tmp_path)]) == 2
    out, err = capsys.readouterr()
    assert err == f"error: cannot serve on 127.0.0.1:{port} (Cannot find empty port in range: 7998-7998); pass " \
                  "another --port\n"
    assert "serving" not in out
