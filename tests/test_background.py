"""Background removal (:mod:`depthnerf.reconstruct.background`): a car render pasted on a bright textured
background is cut out by a tiny ONNX model that the test builds (the real rembg loading and segmentation code
runs), against the render's own alpha; ``depthnerf reconstruct`` writes the cut-out and the reconstruction; an
RGBA photo never reaches the model; without rembg, without weights, with removal off or with a bad model file:
exit 2 and one line that says what is missing and how to get it."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
from fixtures_background import cluttered_car, iou, tiny_u2net
from PIL import Image

from depthnerf.app.logic import background_installed
from depthnerf.cli import main
from depthnerf.data.synth.framing import get_framing
from depthnerf.errors import DepthnerfError
from depthnerf.reconstruct.background import BackgroundRemover, choose_remover, download_command
from depthnerf.reconstruct.photo import prepare_photo
from depthnerf.reconstruct.reconstructor import ReconstructConfig, Reconstructor

CLUTTER = "the background is not a plain colour"


@pytest.fixture(scope="module")
def photo(tmp_path_factory) -> tuple[Path, np.ndarray]:
    rgb, truth = cluttered_car()
    path = tmp_path_factory.mktemp("bg") / "van_on_tiles.png"
    Image.fromarray(rgb).save(path)
    return path, truth


@pytest.fixture(scope="module")
def models(tmp_path_factory) -> dict[str, Path]:
    if not background_installed():  # not imported here: depthnerf imports rembg itself (background.py)
        pytest.skip("rembg is not installed (pip install -e '.[bg]')")
    pytest.importorskip("onnx", reason="onnx builds the test's model (pip install -e '.[dev]')")
    tmp = tmp_path_factory.mktemp("bg_models")
    return {"dark": tiny_u2net(tmp / "tiny_dark.onnx", -1.0), "bright": tiny_u2net(tmp / "tiny_bright.onnx", 1.0)}


def reconstruct(photo: Path, out: Path, *flags: str) -> int:
    return main(["reconstruct", str(photo), "--checkpoint", "cpu-cars-depth", "--out", str(out), "--views", "1",
                 "--mesh-resolution", "16", "--no-progress", *flags])


def test_reconstruct_cuts_the_object_out_with_a_model_file(photo, models, tmp_path, capsys):
    path, truth = photo
    assert reconstruct(path, tmp_path / "out", "--background-model", str(models["dark"])) == 0
    out = tmp_path / "out"
    manifest = json.loads((out / "manifest.json").read_text())
    cutout = np.asarray(Image.open(out / manifest["files"]["cutout"]))
    assert cutout.shape == (*truth.shape, 4)
    assert iou(cutout[..., 3] > 127, truth) > 0.95  # the model's mask, against the render's own alpha
    assert np.array_equal(cutout[..., :3], np.asarray(Image.open(path)))
    settings = manifest["settings"]
    assert settings["background_model"] == "tiny_dark.onnx" and settings["background_removal"] == "auto"
    notes = manifest["input"]["notes"]
    assert any("background removed by the tiny_dark.onnx model" in n for n in notes) and "mask: alpha > 0.5" in notes
    # the cut-out is recentred at the checkpoint's training fill: the longer mask side is fill x 64 px
    mask = np.asarray(Image.open(out / "input_mask.png")) > 0
    rows, cols = np.where(mask.any(1))[0], np.where(mask.any(0))[0]
    side = max(rows[-1] - rows[0], cols[-1] - cols[0]) + 1
    assert abs(side - get_framing("srn").fill("cars", 0.0) * 64) <= 2
    image = np.asarray(Image.open(out / "input.png"), np.float32) / 255
    assert image[~mask].min() > 0.99  # the tiles are gone: white around the object
    assert len(manifest["files"]["views"]) == 1 and (out / "mesh.glb").is_file()
    assert "wrote 1 views" in capsys.readouterr().out
    # the cut-out is one of the files a reconstruction owns: --overwrite with a photo that needs no model removes it
    plain = Path(__file__).parents[1] / "depthnerf/app/examples/chair_white.png"
    assert reconstruct(plain, out, "--overwrite", "--mesh-resolution", "0") == 0
    assert json.loads((out / "manifest.json").read_text())["files"]["cutout"] is None
    assert not (out / "cutout.png").exists()


def test_the_mask_is_the_models_output(photo, models):
    """The brightness model selects the tiles instead: the mask follows the model, not the image."""
    path, truth = photo
    dark = prepare_photo(path, None, 64, background=choose_remover("on", str(models["dark"])))
    bright = prepare_photo(path, None, 64, background=choose_remover("on", str(models["bright"])))
    assert iou(dark.cutout[..., 3] > 0.5, truth) > 0.95
    assert iou(bright.cutout[..., 3] > 0.5, ~truth) > 0.95


def test_the_default_model_is_read_from_rembgs_model_folder(photo, models, tmp_path, monkeypatch):
    path, truth = photo
    monkeypatch.setenv("U2NET_HOME", str(tmp_path))
    shutil.copyfile(models["dark"], tmp_path / "u2net.onnx")  # where rembg's download_models puts it
    prep = prepare_photo(path, None, 64, background=choose_remover("auto"))
    assert iou(prep.cutout[..., 3] > 0.5, truth) > 0.95
    assert any("by the u2net model" in n for n in prep.notes)


class Spy:
    """A rembg-like session that counts its calls and finds nothing."""

    def __init__(self) -> None:
        self.calls = 0

    def predict(self, image: Image.Image) -> list[Image.Image]:
        self.calls += 1
        return [Image.new("L", image.size, 0)]


def test_an_rgba_photo_or_a_given_mask_never_reaches_the_model(photo):
    path, truth = photo
    spy = Spy()
    remover = BackgroundRemover(spy, "spy")
    rgba = np.dstack([np.asarray(Image.open(path)), truth.astype(np.uint8) * 255])
    prep = prepare_photo(rgba, None, 64, background=remover)
    assert spy.calls == 0 and prep.cutout is None and "mask: alpha > 0.5" in prep.notes
    prep = prepare_photo(path, truth.astype(np.uint8) * 255, 64, background=remover)
    assert spy.calls == 0 and prep.cutout is None
    with pytest.raises(DepthnerfError, match="no object found"):  # an RGB photo does reach it (empty mask here)
        prepare_photo(path, None, 64, background=remover)
    assert spy.calls == 1
    with pytest.raises(DepthnerfError, match="no object found"):  # and through the API's own-remover argument
        Reconstructor.from_pretrained("cpu-cars-depth").reconstruct(path, background=remover)
    assert spy.calls == 2


def one_line_error(capsys, code: int) -> str:
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    return err


def test_without_rembg_the_cluttered_photo_says_how_to_install_it(photo, tmp_path, capsys, monkeypatch):
    path, _ = photo
    monkeypatch.setitem(sys.modules, "rembg", None)  # find_spec -> None, as when the extra is not installed
    err = one_line_error(capsys, reconstruct(path, tmp_path / "out"))
    assert err.startswith(f"error: {path}: {CLUTTER}")
    assert ("background removal needs rembg, which is not installed: pip install 'depthnerf[bg]', then "
            "`python -c \"from rembg.bg import download_models; download_models(['u2net'])\"` for its weights; "
            "or use an RGBA cut-out") in err
    assert not (tmp_path / "out").exists()
    err = one_line_error(capsys, reconstruct(path, tmp_path / "out", "--background-removal", "on"))
    assert err.startswith(f"error: {path}: background removal needs rembg")


def test_without_weights_the_cluttered_photo_says_how_to_get_them(photo, models, tmp_path, capsys):
    path, _ = photo
    err = one_line_error(capsys, reconstruct(path, tmp_path / "out"))
    assert err.startswith(f"error: {path}: {CLUTTER}") and "the background model u2net is not downloaded: run " \
        f"`{download_command('u2net')}` where there is internet" in err and "--background-model FILE.onnx" in err
    err = one_line_error(capsys, reconstruct(path, tmp_path / "out", "--background-model", "isnet-general-use"))
    assert err.startswith("error: the background model isnet-general-use is not downloaded")
    err = one_line_error(capsys, reconstruct(path, tmp_path / "out", "--background-removal", "off"))
    assert f"{CLUTTER}" in err and "background removal is off" in err
    err = one_line_error(capsys, reconstruct(path, tmp_path / "out", "--background-removal", "off",
                                             "--background-model", str(models["dark"])))
    assert err == ("error: --background-model applies only when the background is removed (drop "
                   "--background-removal off)\n")  # a model that would not run is refused, not ignored
    assert reconstruct(Path(__file__).parents[1] / "depthnerf/app/examples/chair_white.png",
                       tmp_path / "plain") == 0  # a plain background needs no model in auto mode


def test_bad_model_names_and_files_are_one_line(photo, models, tmp_path, capsys):
    path, _ = photo
    err = one_line_error(capsys, reconstruct(path, tmp_path / "o", "--background-model", "bria-rmbg"))
    assert err.startswith("error: --background-model bria-rmbg: not a model file and not one of u2net, ")
    (tmp_path / "notes.onnx").write_text("not a graph\n")
    err = one_line_error(capsys, reconstruct(path, tmp_path / "o", "--background-model", str(tmp_path / "notes.onnx")))
    assert err.startswith(f"error: {tmp_path / 'notes.onnx'}: not a loadable ONNX background model")
    err = one_line_error(capsys, reconstruct(path, tmp_path / "o", "--background-model", str(tmp_path / "no.onnx")))
    assert err.startswith(f"error: {tmp_path / 'no.onnx'}: background model file not found")
    with pytest.raises(DepthnerfError, match=r"^--background-removal must be one of auto, on, off, got 'yes'$"):
        ReconstructConfig(background_removal="yes")  # the API's config is checked as the flag is
