"""Flags that cannot work, or that contradict each other, are one ``error:`` line naming the flag (exit status 2)
before any model loads or any work starts: never a traceback, never a flag quietly left unused.

Each case here was once a traceback (``depth-eval`` on a folder without datasets, ``fit-facing --seed -1``,
``train --model.encoder.image_scale inf``), an exit status 0 on nothing (``depth --depth oracle`` on a folder
without datasets or with flags that cannot work), or a flag silently dropped (``eval --symmetry-plane`` with
``--no-symmetry``, ``reconstruct --fill`` with ``--framing keep``, ``--background-model`` with
``--background-removal off``, ``--facing-min-confidence`` without ``--facing auto``, ``--guided-align-samples``
without ``--guided``, ``app --background-model`` or a later ``app --checkpoint`` naming a file that is not there,
``demo --cars-checkpoint`` with ``--categories chairs``, a mesh flag with ``eval --no-mesh``, ``demo --no-mesh``
or ``reconstruct --mesh-resolution 0``)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from depthnerf.cli import main
from depthnerf.errors import DepthnerfError
from depthnerf.model.config import EncoderConfig, FieldConfig
from tests.fixtures_srn import make_srn_fixture

PHOTO = Path(__file__).resolve().parent.parent / "depthnerf" / "app" / "examples" / "car_rgba.png"


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    return make_srn_fixture(tmp_path_factory.mktemp("flag_refusals") / "data", "cars", {"train": 1, "test": 1},
                            views=2, size=16, with_depth=True)


def _one_error(capsys) -> str:
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1, err
    return err.strip()


def test_depth_eval_on_a_folder_without_datasets_is_one_line(tmp_path, capsys):
    """It was an IndexError traceback (no records, then ``records[0]``)."""
    assert main(["depth-eval", "--data", str(tmp_path), "--depth", "oracle", "--no-progress"]) == 2
    assert _one_error(capsys) == f"error: {tmp_path}: no <category>_<split> folders found"


@pytest.mark.parametrize("estimator", ["oracle", "none"])
@pytest.mark.parametrize("flags, line", [
    ([], "{empty}: no <category>_<split> folders found"),
    (["--category", "trucks"], "{data}: --category trucks: no trucks_<split> folder (train, val, test) exists here "
                               "(categories here: cars)"),
    (["--batch-size", "0"], "--batch-size must be positive, got 0"),
    (["--resolution", "-16"], "--resolution must be >= 8, got -16"),
])
def test_depth_without_a_cache_checks_the_request_as_a_cached_estimator_does(data, tmp_path, capsys, estimator,
                                                                            flags, line):
    """``oracle`` and ``none`` cache nothing, but said "needs no cache" with exit status 0 to any of these."""
    root = tmp_path if not flags else data
    assert main(["depth", "--data", str(root), "--depth", estimator, "--no-progress", *flags]) == 2
    assert _one_error(capsys) == "error: " + line.format(empty=tmp_path, data=data)
    assert main(["depth", "--data", str(data), "--depth", estimator, "--no-progress"]) == 0
    assert "needs no cache" in capsys.readouterr().out


@pytest.mark.parametrize("inside", ["", "cars_train/run", "cars_val"])
def test_train_refuses_an_out_inside_the_dataset(tmp_path, capsys, inside):
    """The run folder became an object of a split (the next read refused the dataset) or, as ``cars_val``, a split
    of its own; refused before the run folder is made, also on ``--resume``."""
    root = make_srn_fixture(tmp_path / "data", "cars", {"train": 1}, views=2, size=16)
    before = sorted(root.rglob("*"))
    out = root / inside
    for resume in ([], ["--resume"]):
        assert main(["train", "--data", str(root), "--out", str(out), "--depth", "none", "--max-steps", "1",
                     "--data.resolution", "32", "--log.val_every", "0", "--no-progress", *resume]) == 2
        assert _one_error(capsys) == (f"error: {out}: --out is the dataset {root} or lies in one of its split "
                                      "folders, which training reads; choose an --out outside them")
    assert sorted(root.rglob("*")) == before


def test_fit_facing_refuses_a_negative_seed_before_loading(tmp_path, capsys):
    """It was numpy's ValueError traceback once the views were drawn."""
    assert main(["fit-facing", "--checkpoint", str(tmp_path / "none.safetensors"), "--data", str(tmp_path),
                 "--category", "cars", "--out", str(tmp_path / "out.safetensors"), "--seed", "-1"]) == 2
    assert _one_error(capsys) == "error: --seed must be >= 0, got -1"


@pytest.mark.parametrize("device, line", [
    ("nope", "--device nope: choose cpu, cuda or cuda:N"),
    ("auto", "--device auto: choose cpu, cuda or cuda:N"),
])
def test_fit_facing_refuses_a_device_it_cannot_use_before_loading(tmp_path, capsys, device, line):
    """It was checked when the model loaded, after the checkpoint and the data, in words without the flag."""
    assert main(["fit-facing", "--checkpoint", str(tmp_path / "none.safetensors"), "--data", str(tmp_path),
                 "--category", "cars", "--out", str(tmp_path / "out.safetensors"), "--device", device]) == 2
    assert _one_error(capsys) == f"error: {line}"


def test_model_configs_refuse_an_infinite_image_scale_and_a_frequency_base_that_is_not_positive(tmp_path, capsys):
    """``image_scale inf`` passed the config and ended in an OverflowError traceback (``floor(inf)``); a base
    frequency of 0 made every sin/cos of the positional encoding a constant."""
    for scale in (math.inf, -math.inf, math.nan, 0.0):
        with pytest.raises(DepthnerfError, match="encoder.image_scale must be a finite number > 0"):
            EncoderConfig(image_scale=scale)
    for factor in (0.0, -1.5, math.inf, math.nan):
        with pytest.raises(DepthnerfError, match="field.freq_factor must be a finite number > 0"):
            FieldConfig(freq_factor=factor)
    assert main(["train", "--data", str(tmp_path), "--out", str(tmp_path / "run"), "--model.encoder.image_scale",
                 "inf", "--print-config"]) == 2
    assert "encoder.image_scale must be a finite number > 0, got inf" in _one_error(capsys)
    assert not (tmp_path / "run").exists()


def test_eval_refuses_a_symmetry_plane_with_no_symmetry(tmp_path, capsys):
    """The plane was silently dropped (``--no-symmetry`` won); checked before the checkpoint loads."""
    assert main(["eval", "--checkpoint", str(tmp_path / "none.safetensors"), "--out", str(tmp_path / "out"),
                 "--symmetry-plane", "1", "0", "0", "0", "--no-symmetry"]) == 2
    assert _one_error(capsys) == ("error: --symmetry-plane and --no-symmetry contradict each other: pass one of "
                                  "them")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("flags, line", [
    (["--mesh-resolution", "64"], "--mesh-resolution sets the mesh, which --no-mesh skips: pass one or the other"),
    (["--fscore-tau", "0.02", "--mesh-points", "1000"],
     "--fscore-tau --mesh-points set the mesh, which --no-mesh skips: pass one or the other"),
])
def test_eval_refuses_mesh_flags_with_no_mesh(tmp_path, capsys, flags, line):
    """Each was accepted and ignored (no mesh is made, so nothing used it); checked before the checkpoint loads."""
    assert main(["eval", "--checkpoint", str(tmp_path / "none.safetensors"), "--out", str(tmp_path / "out"),
                 "--no-mesh", *flags]) == 2
    assert _one_error(capsys) == f"error: {line}"
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("command", ["eval", "reconstruct"])
def test_guided_align_samples_needs_guided(tmp_path, capsys, command):
    """It set the alignment render of a guided sampler that does not run (nothing said so)."""
    head = (["eval", "--checkpoint", str(tmp_path / "none.safetensors")] if command == "eval"
            else ["reconstruct", str(PHOTO), "--checkpoint", str(tmp_path / "none.safetensors")])
    assert main([*head, "--out", str(tmp_path / "out"), "--guided-align-samples", "16"]) == 2
    assert _one_error(capsys) == "error: --guided-align-samples 16 applies only with --guided"
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("flags, line", [
    (["--fill", "0.5", "--framing", "keep"], "--fill applies only with --framing auto (keep only pads the photo "
                                             "to a square)"),
    (["--background-model", "u2net", "--background-removal", "off"],
     "--background-model applies only when the background is removed (drop --background-removal off)"),
    (["--facing-min-confidence", "0.5"], "--facing-min-confidence applies only with --facing auto"),
    (["--facing", "90", "--facing-min-confidence", "0.5"], "--facing-min-confidence applies only with --facing auto"),
    (["--mesh-resolution", "0", "--mesh-keep", "largest"],
     "--mesh-keep applies only to the mesh, which --mesh-resolution 0 skips: pass one or the other"),
    (["--mesh-resolution", "0", "--mesh-threshold", "auto", "--mesh-fill", "0"],
     "--mesh-threshold --mesh-fill apply only to the mesh, which --mesh-resolution 0 skips: pass one or the other"),
])
def test_reconstruct_refuses_flags_another_flag_turns_off(tmp_path, capsys, flags, line):
    """Each was accepted and had no effect; refused before the output folder is made or the checkpoint loads."""
    assert main(["reconstruct", str(PHOTO), "--checkpoint", str(tmp_path / "none.safetensors"), "--out",
                 str(tmp_path / "out"), *flags]) == 2
    assert _one_error(capsys) == f"error: {line}"
    assert not (tmp_path / "out").exists()


def test_app_refuses_a_background_model_that_is_not_there_before_serving(tmp_path, capsys, monkeypatch):
    """It served the page, and every photo without alpha then failed on the missing file."""
    pytest.importorskip("gradio")
    import depthnerf.app.page as page

    def never(*args, **kwargs):
        raise AssertionError("the app started serving")

    monkeypatch.setattr(page, "serve", never)
    missing = tmp_path / "missing.onnx"
    assert main(["app", "--background-model", str(missing), "--port", "7999"]) == 2
    assert _one_error(capsys) == f"error: {missing}: background model file not found"
    assert main(["app", "--background-model", "no-such-model", "--port", "7999"]) == 2
    assert _one_error(capsys).startswith("error: --background-model no-such-model: not a model file and not one of ")


def test_app_refuses_a_menu_checkpoint_that_is_not_there_before_serving(tmp_path, capsys, monkeypatch):
    """Only the menu's first checkpoint was loaded at start: a later one that is not there was served, and failed
    when chosen."""
    pytest.importorskip("gradio")
    import depthnerf.app.page as page

    def never(*args, **kwargs):
        raise AssertionError("the app started serving")

    monkeypatch.setattr(page, "serve", never)
    missing = tmp_path / "missing.safetensors"
    assert main(["app", "--checkpoint", "cpu-cars-sym-pp", str(missing), "--port", "7999"]) == 2
    assert _one_error(capsys).startswith(f"error: --checkpoint {missing}: not a checkpoint file")


def test_demo_refuses_a_checkpoint_for_a_category_it_leaves_out(tmp_path, capsys):
    """``--cars-checkpoint`` was ignored when ``--categories`` named chairs only."""
    out = tmp_path / "demo"
    assert main(["demo", "--categories", "chairs", "--cars-checkpoint", str(tmp_path / "m.safetensors"),
                 "--out", str(out), "--no-progress"]) == 2
    assert _one_error(capsys) == ("error: --cars-checkpoint is given but --categories chairs leaves cars out: add "
                                  "cars to --categories or drop --cars-checkpoint")
    assert not out.exists()


def test_demo_refuses_a_mesh_resolution_with_no_mesh(tmp_path, capsys):
    """``--mesh-resolution`` was accepted with ``--no-mesh`` and ignored, as ``eval`` refuses it."""
    out = tmp_path / "demo"
    assert main(["demo", "--no-mesh", "--mesh-resolution", "64", "--out", str(out), "--no-progress"]) == 2
    assert _one_error(capsys) == "error: --mesh-resolution sets the mesh, which --no-mesh skips: pass one or the other"
    assert not out.exists()
