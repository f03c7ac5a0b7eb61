"""``depthnerf app``: what requests share and what a public page accepts.

Run folders: two app processes on one ``--work-dir`` (two :class:`AppSession` here) never write into the same run
folder, and the oldest beyond ``keep_runs`` go. A page served with ``--share`` hides its path fields; its HTTP API
takes the same parameters, so the session itself refuses a request naming a local file or folder of the server or a
model outside the menu (checked here on :meth:`AppSession.preview` and :meth:`AppSession.run`, the functions the
API calls). Odd uploads: an animated PNG or WebP is read as its first frame, with a note.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from PIL import Image

from depthnerf.app.logic import AppConfig, AppSession, RunRequest, examples
from depthnerf.app.messages import check_local_paths
from depthnerf.errors import DepthnerfError
from depthnerf.pretrained.load import shipped_checkpoints


def test_two_processes_on_one_work_dir_get_their_own_run_folders(tmp_path):
    first, second = (AppSession(AppConfig(mesh_resolution=0, work_dir=tmp_path, keep_runs=3)) for _ in range(2))
    folders = [first._new_run_dir(), second._new_run_dir(), first._new_run_dir()]
    assert len(set(folders)) == 3 and all(f.is_dir() for f in folders), folders
    assert [f.name for f in folders] == ["run-000001", "run-000002", "run-000003"]
    second._new_run_dir()  # the fourth: the oldest goes (keep_runs=3), whoever made it
    assert sorted(d.name for d in tmp_path.glob("run-*")) == ["run-000002", "run-000003", "run-000004"]
    # a whole request each: each one's outputs stay its own
    outs = [session.run(RunRequest(examples()[0], "car", views=views))
            for session, views in ((first, 1), (second, 2))]
    assert all(o.ok for o in outs) and outs[0].input_image.parent != outs[1].input_image.parent
    for out, views in zip(outs, (1, 2), strict=True):
        assert json.loads((out.input_image.parent / "manifest.json").read_text())["settings"]["views"] == views


@pytest.fixture(scope="module")
def shared(tmp_path_factory) -> AppSession:
    return AppSession(AppConfig(mesh_resolution=0, work_dir=tmp_path_factory.mktemp("shared"),
                                allow_checkpoint_paths=False))


def test_a_shared_page_refuses_local_paths_whichever_way_they_come(shared, tmp_path):
    weights = str(shipped_checkpoints()["cpu-cars-depth"])  # a real checkpoint file on the server
    onnx = tmp_path / "model.onnx"
    onnx.write_bytes(b"not a graph")
    folder = tmp_path / "da-weights"
    folder.mkdir()
    cases = {
        "checkpoint path": (RunRequest(examples()[0], "car", checkpoint_path=weights), "local checkpoint paths are off"),
        "background file": (RunRequest(examples()[0], "car", background_model=str(onnx)),
                            "background model '" + str(onnx) + "': local files are off"),
        "DA folder": (RunRequest(examples()[0], "car", depth_checkpoint=str(folder)), "local folders are off"),
        "relative DA": (RunRequest(examples()[0], "car", depth_checkpoint="../weights"), "local folders are off"),
        "model off the menu": (RunRequest(examples()[0], "cpu-cars-depth"), "not in this page's menu"),
    }
    for kind, (request, text) in cases.items():
        image, message = shared.preview(request)
        assert image is None and message.startswith("error: ") and text in message, (kind, message)
        out = shared.run(request)
        assert not out.ok and text in out.message and "\n" not in out.message, (kind, out.message)
    assert shared.training_fill("car") > 0
    with pytest.raises(DepthnerfError, match="local checkpoint paths are off"):
        shared.training_fill("car", weights)
    image, message = shared.preview(RunRequest(examples()[0], "car", background_model="u2net", remove_background=False,
                                               depth_checkpoint="depth-anything/Depth-Anything-V2-Small-hf"))
    assert message.startswith("ready: "), message  # model names and hub ids pass (nothing loads them here)
    local = AppSession(AppConfig(mesh_resolution=0, work_dir=tmp_path / "local"))  # not shared: paths work
    assert local.preview(RunRequest(examples()[0], "car", checkpoint_path=weights))[1].startswith("ready: ")


def test_hub_ids_and_names_pass_the_shared_rule():
    check_local_paths("", "u2net", "depth-anything/Depth-Anything-V2-Base-hf")
    check_local_paths("", "", "")
    for background, weights in (("sub/u2net", ""), ("", "/abs/dir"), ("", "~/weights"), ("", "a/b/c"),
                                ("x.onnx", ""), ("", "name-only")):
        with pytest.raises(DepthnerfError, match="off on this shared page"):
            check_local_paths("", background, weights)


@pytest.mark.parametrize("suffix", ["png", "webp"])
def test_an_animated_upload_is_read_as_its_first_frame_with_a_note(shared, tmp_path, suffix):
    car = Image.open(examples()[0])
    still = Image.new("RGB", car.size, (255, 255, 255))
    still.paste(car, mask=car.getchannel("A"))
    path = tmp_path / f"anim.{suffix}"
    still.save(path, save_all=True, append_images=[Image.new("RGB", car.size, (255, 255, 255))], duration=100,
               **({"lossless": True} if suffix == "webp" else {}))
    image, message = shared.preview(RunRequest(path, "car"))
    first, _ = shared.preview(RunRequest(_write_still(still, tmp_path / f"still.{suffix}"), "car"))
    assert "animated image: the first of its 2 frames is used" in message, message
    assert image is not None and (image == first).all()


def _write_still(im: Image.Image, path: Path) -> Path:
    im.save(path, **({"lossless": True} if path.suffix == ".webp" else {}))
    return path
