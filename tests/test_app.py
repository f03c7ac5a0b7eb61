"""``depthnerf app`` without a browser: the plain functions of :mod:`depthnerf.app.logic` (upload checks, one-line
messages for every kind of bad input in the page's words, a real run through the shipped checkpoint and the files
it collects, background removal, the depth prior's weights and licence), the page's wiring (a new upload clears
every earlier output), the command (install hint without gradio, bind address, queue, the temporary folder
removed on SIGTERM) and the promise that the core never imports gradio."""

from __future__ import annotations

import importlib.util
import json
import os
import re
import signal
import socket
import struct
import subprocess
import sys
import time
import zlib
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh
from PIL import Image

from depthnerf.app.logic import (
    DEPTH_PRIORS,
    AppConfig,
    AppSession,
    ModelCache,
    RunRequest,
    background_installed,
    examples,
    resolve_model,
)
from depthnerf.app.messages import check_upload, one_line, prior_description
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
                          "error: blank.png: no object found (every pixel has the border's colour); upload an RGBA "
                          "cut-out"),
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
    for views in (0, 37, 2.7, float("nan"), None, "8"):  # the page's slider sends whole numbers; its API anything
        message = session.run(RunRequest(example, "car", views=views)).message
        assert message == f"error: orbit views must be a whole number within 1..36, got {views}", message
    assert session.run(RunRequest(example, "car", elevation=None)).message == \
        "error: the elevation must be a number, got None"
    assert session.run(RunRequest(example, "car", facing="front")).message == \
        "error: the object facing must be a number, got 'front'"
    assert session.run(RunRequest(example, "car", foreground_ratio=1.5)).message.startswith(
        "error: foreground ratio must be within 0.05..1")
    out = session.run(RunRequest(example, "car", depth_prior="midas"))
    assert out.message.startswith("error: depth prior must be one of trained, bundled, depth-anything-v2")
    assert not out.ok
    out = session.run(RunRequest(example, "car", depth_prior="depth-anything-v2",
                                 depth_checkpoint=str(tmp_path / "no-da-weights")))
    assert out.message.startswith("error: ") and "no-da-weights" in out.message and "\n" not in out.message
    out = session.run(RunRequest(example, "car", mesh_level="median"))
    assert out.message == "error: mesh level must be one of auto, silhouette, local, got 'median'" and not out.ok
    out = session.run(RunRequest(example, "car", mesh_colors="texture"))
    assert out.message == "error: mesh colours must be one of normal-ray, photo, point, got 'texture'" and not out.ok
    out = session.run(RunRequest(example, "car", checkpoint_path=str(tmp_path / "nope.safetensors")))
    assert out.message.startswith("error: ") and "nope.safetensors" in out.message and "\n" not in out.message


def test_the_preview_refuses_the_foreground_ratios_the_run_refuses(session):
    """The preview (also the page's HTTP API ``/preview``) showed a framing at a ratio the run then refused, and
    took 0 for the training fill."""
    example = examples()[0]
    for ratio in (0.0, 0.01, 1.5):
        run = session.run(RunRequest(example, "car", views=1, foreground_ratio=ratio)).message
        image, preview = session.preview(RunRequest(example, "car", foreground_ratio=ratio))
        assert image is None and preview == run == f"error: foreground ratio must be within 0.05..1, got {ratio}"
    image, preview = session.preview(RunRequest(example, "car", foreground_ratio=0.05))
    assert image is not None and preview.startswith("ready: ")


def test_resolve_model_and_messages(tmp_path):
    assert resolve_model(RunRequest(None, "car")) == "cpu-cars-sym-pp"
    assert resolve_model(RunRequest(None, "chair")) == "cpu-chairs-sym-pp"
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
        "cpu-cars-sym-pp.safetensors"
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
    rule = manifest["settings"]["mesh_level_rule"]  # the page's default
    assert rule.startswith("local level: half the peak density along each input ray")
    auto = session.run(RunRequest(examples()[0], "car", views=1, mesh_level="auto", mesh_colors="normal-ray"))
    settings = json.loads((auto.input_image.parent / "manifest.json").read_text())["settings"]
    assert settings["mesh_level_rule"].startswith("auto level")
    assert manifest["settings"]["mesh_colors"].startswith("the input photo's rgb")  # the page's default
    assert manifest["settings"]["mesh_color_rule"] == "photo" and ", photo colours, " in out.details
    assert settings["mesh_color_rule"] == "normal-ray" and ", normal-ray colours, " in auto.details
    assert settings["mesh_colors"].startswith("fine-network rgb volume-rendered along each vertex's inward normal")
    # the page renders depth-guided by default; unticked, with the checkpoint's own sampler
    assert manifest["settings"]["guided_sampling"] == 48 and "depth-guided sampling (48 samples" in out.details
    assert settings["guided_sampling"] == 48
    plain = session.run(RunRequest(examples()[0], "car", views=1, guided=False))
    assert not json.loads((plain.input_image.parent / "manifest.json").read_text())["settings"]["guided_sampling"]
    assert "the model's own sampler" in plain.details
    # keep_runs=2: older run folders are deleted as new ones come
    for _ in range(2):
        session.run(RunRequest(examples()[0], "car", views=1))
    assert len(list(session.work_dir.glob("run-*"))) == 2 and not run.exists()
    later = AppSession(AppConfig(work_dir=session.work_dir))  # a reused work folder: new runs, never old names
    before = max(d.name for d in session.work_dir.glob("run-*"))
    assert later._new_run_dir().name > before


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


def flags_outside_commands(message: str) -> list[str]:
    """Command-line flags a page message still names (shell commands in backticks are fine: they are run
    elsewhere)."""
    return re.findall(r"--[a-z][a-z-]*", re.sub(r"`[^`]*`", "", message))


def test_messages_speak_the_pages_language(session, tmp_path, monkeypatch):
    """No ``--flag`` of depthnerf in what the page shows: the flags a message suggests become the page's fields."""
    import huggingface_hub.constants

    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)  # no network attempt
    bad = bad_inputs(tmp_path)
    scene, blank = bad["cluttered"][0], bad["no foreground"][0]
    removal_hint = ("enter FILE.onnx under 'Background model'" if background_installed()
                    else "pip install 'depthnerf[bg]'")  # the hint names what is missing: weights, or the extra
    cases = {
        "clutter, removal on": (RunRequest(scene, "car"), removal_hint),
        "clutter, removal off": (RunRequest(scene, "car", remove_background=False),
                                 "background removal is off (tick 'Remove background')"),
        "no object": (RunRequest(blank, "car"), "upload an RGBA cut-out of the object"),
        "bad background model": (RunRequest(scene, "car", background_model="bria-rmbg"),
                                 "error: background model bria-rmbg: not a model file"),
        "depth anything offline": (RunRequest(examples()[0], "car", depth_prior="depth-anything-v2",
                                              depth_checkpoint="someone/not-cached-here"),
                                   "enter DIR under 'Depth Anything V2 weights'"),
    }
    for kind, (request, expected) in cases.items():
        message = session.run(request).message
        assert expected in message and not flags_outside_commands(message), (kind, message)
        if kind != "depth anything offline":  # the preview does not load a depth prior
            preview = session.preview(request)[1]
            assert expected in preview and not flags_outside_commands(preview), (kind, preview)


def test_the_trained_prior_is_the_checkpoints_own_and_the_weights_field_is_for_depth_anything(monkeypatch):
    """The page's default prior is the one the checkpoint was trained with (a Depth Anything model keeps Depth
    Anything, as ``reconstruct`` without ``--depth``); the weights field reaches only a Depth Anything prior."""
    import depthnerf
    import depthnerf.pretrained.load as load

    trained = {"estimator": "depth-anything-v2"}
    monkeypatch.setattr(load, "load_pretrained", lambda checkpoint, device: SimpleNamespace(
        spec=SimpleNamespace(depth_aware=True, prior=SimpleNamespace(estimator=trained["estimator"]))))
    calls = []
    monkeypatch.setattr(depthnerf.Reconstructor, "from_pretrained",
                        classmethod(lambda cls, pre, device, **kw: calls.append(kw) or kw))
    cache = ModelCache()
    assert cache.get("da.safetensors") == {"depth_checkpoint": None, "depth_estimator": "depth-anything-v2"}
    assert cache.get("da.safetensors", "trained", "dir/small")["depth_checkpoint"] == "dir/small"
    assert cache.get("da.safetensors", "bundled", "dir/small") == {"depth_checkpoint": None,
                                                                     "depth_estimator": "bundled"}
    trained["estimator"] = "bundled"
    assert cache.get("b.safetensors", "trained", "dir/small") == {"depth_checkpoint": None,
                                                                  "depth_estimator": "bundled"}
    assert cache.get("b.safetensors", "depth-anything-v2", "dir/small")["depth_checkpoint"] == "dir/small"
    assert len(calls) == 5
    assert RunRequest("x.png", "car").depth_prior == "trained"


def test_prior_choice_names_the_weights_it_loads_and_their_licence():
    assert prior_description("trained").startswith("as trained: the prior the chosen model was trained with")
    assert prior_description("bundled").endswith("(MIT)")
    base = prior_description("depth-anything-v2")
    assert base.startswith("Depth Anything V2 Base (depth-anything/Depth-Anything-V2-Base-hf, the paper's prior)")
    assert "CC-BY-NC-4.0" in base and "non-commercial" in base
    small = prior_description("depth-anything-v2", "depth-anything/Depth-Anything-V2-Small-hf")
    assert small.startswith("Depth Anything V2 Small") and "Apache-2.0" in small


def test_background_removal_runs_in_the_app(session, tmp_path):
    if not background_installed():  # not imported here: depthnerf imports rembg itself (background.py)
        pytest.skip("rembg is not installed (pip install -e '.[bg]')")
    pytest.importorskip("onnx", reason="onnx builds the test's model")
    from fixtures_background import cluttered_car, iou, tiny_u2net

    rgb, truth = cluttered_car()
    photo = tmp_path / "van.jpg"
    Image.fromarray(rgb).save(photo, quality=95)
    model = str(tiny_u2net(tmp_path / "tiny.onnx"))
    image, message = session.preview(RunRequest(photo, "car", background_model=model))
    assert image is not None and "background removed by the tiny.onnx model" in message, message
    out = session.run(RunRequest(photo, "car", views=1, background_model=model))
    assert out.ok and "**Background** removed by the tiny.onnx model" in out.details, out.message
    cutout = np.asarray(Image.open(out.input_image.parent / "cutout.png"))
    assert iou(cutout[..., 3] > 127, truth) > 0.9
    off = session.run(RunRequest(photo, "car", views=1, background_model=model, remove_background=False))
    assert not off.ok and "background is not a plain colour" in off.message


def test_a_new_upload_clears_every_earlier_output(session, tmp_path):
    """The page's upload event writes every output the reconstruction writes: an error or a new photo leaves no
    earlier depth prior, orbit, mesh or download on the page."""
    pytest.importorskip("gradio", reason="gradio is not installed (pip install -e '.[app]')")
    from depthnerf.app.page import PRIOR_CHOICES, build_page

    assert [value for _, value in PRIOR_CHOICES] == list(DEPTH_PRIORS)
    page = build_page(session)
    fns = {f.name: f for f in page.fns.values()}
    ids = {name: [getattr(b, "elem_id", None) for b in fns[name].outputs] for name in ("preview", "reconstruct")}
    assert set(ids["reconstruct"]) <= set(ids["preview"]), ids
    notes = tmp_path / "notes.png"
    notes.write_text("not pixels")
    for image in (notes, examples()[0], None):
        values = dict(zip(ids["preview"], fns["preview"].fn(str(image) if image else None, "car", "", None, True, ""),
                          strict=True))
        assert all(values[k] in (None, "") for k in ("prior-image", "video", "gif", "viewer", "downloads",
                                                      "details")), values
        assert (values["prepared"] is not None) == (image == examples()[0])


def test_choosing_a_model_sets_its_fill_and_facing_box_unless_the_checkpoint_is_bad(session, monkeypatch):
    """Choosing a model sets the fill slider to its training fill and ticks "Estimate the facing" when it carries a
    facing head; a bad checkpoint keeps both (the run reports it in one line), any other failure is a bug and
    surfaces."""
    pytest.importorskip("gradio", reason="gradio is not installed (pip install -e '.[app]')")
    import gradio as gr

    from depthnerf.app.page import build_page

    defaults_for = {f.name: f for f in build_page(session).fns.values()}["defaults_for"].fn
    fill, auto = defaults_for("car", "")
    assert fill == pytest.approx(session.training_fill("car")) and auto is True  # the shipped car carries a head
    slider, box = defaults_for("car", "/no/such/checkpoint")
    assert isinstance(slider, gr.Slider) and isinstance(box, gr.Checkbox)

    def broken(model, checkpoint_path=""):
        raise RuntimeError("a bug in model_defaults")

    monkeypatch.setattr(session, "model_defaults", broken)
    with pytest.raises(RuntimeError, match="a bug in model_defaults"):
        defaults_for("car", "")


def test_the_temporary_run_folder_is_removed_on_sigterm(monkeypatch, capsys, tmp_path):
    """``depthnerf app`` without --work-dir runs in a temporary folder; SIGTERM (as a service manager stops it)
    ends the server like Ctrl+C, and the folder goes."""
    gr = pytest.importorskip("gradio", reason="gradio is not installed (pip install -e '.[app]')")
    monkeypatch.setenv("TMPDIR", str(tmp_path))
    monkeypatch.setattr("tempfile.tempdir", None)  # re-read TMPDIR

    def serving(self, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(30)  # interrupted by the handler (as Gradio's launch blocks until Ctrl+C)

    monkeypatch.setattr(gr.Blocks, "launch", serving)
    before = signal.getsignal(signal.SIGTERM)
    assert main(["app", "--port", str(free_port())]) == 130
    printed = re.search(r"runs are written to (\S+)\)", capsys.readouterr().out)
    assert printed and Path(printed.group(1)).parent == tmp_path and not Path(printed.group(1)).exists()
    assert signal.getsignal(signal.SIGTERM) == before


def test_the_app_benchmark_calls_the_reconstruct_endpoint_by_its_parameter_names(session):
    """``benchmarks/bench_app.py`` names real parameters of the page's ``/reconstruct`` API and gives every one
    without a default (the client refuses a call without them), so a field added to the page cannot shift its
    call."""
    pytest.importorskip("gradio", reason="gradio is not installed (pip install -e '.[app]')")
    from depthnerf.app.page import build_page

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_app.py"
    spec = importlib.util.spec_from_file_location("bench_app", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    given = bench.reconstruct_arguments("photo.png", "cpu-chairs-sym-pp", 0.43, 8)
    parameters = build_page(session).get_api_info()["named_endpoints"]["/reconstruct"]["parameters"]
    names = {p["parameter_name"] for p in parameters}
    required = {p["parameter_name"] for p in parameters if not p.get("parameter_has_default")}
    assert set(given) <= names, set(given) - names
    assert required <= set(given), required - set(given)
