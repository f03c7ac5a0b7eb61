"""The protocol choices of ``depthnerf eval`` (SSIM variant, scored precision, left-out objects), end to end.

Ground truth: the scores in ``renders.csv`` recomputed from the PNGs on disk (exactly, when the 8-bit PNG is
what was scored) with the textbook PSNR and a brute-force Gaussian SSIM loop; the all-white SRN test car left
out by default and scored with ``--objects all``.
"""

from __future__ import annotations

import csv
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from fixtures_checkpoints import save_tiny, tiny_config
from fixtures_srn import make_srn_fixture
from test_eval_metrics import _gaussian_ssim_reference

from depthnerf.cli import main
from depthnerf.data import srn_format
from depthnerf.eval.config import PIXELNERF_UNLOADABLE, ProtocolChoices
from depthnerf.eval.metrics import SSIM_WINDOWS

WHITE_CAR = "876d92ce6a0e4bf399588eee976baae"
"""SRN's all-white cars test object (the id has 31 hex digits in the release)."""


def cli(*args) -> int:
    return main([str(a) for a in args])


@pytest.fixture(scope="module")
def case(tmp_path_factory) -> dict:
    """2 sphere objects and a copy of the first under the white car's id, every view white (16 px, 66 views)."""
    tmp = tmp_path_factory.mktemp("choices")
    root = make_srn_fixture(tmp / "data", "cars", {"test": 2}, views=66, size=16, with_mask=True)
    white = shutil.copytree(sorted((root / "cars_test").iterdir())[0], root / "cars_test" / WHITE_CAR)
    for png in (white / "rgb").iterdir():
        srn_format.write_rgb(png, np.ones((16, 16, 3), dtype=np.float32))
        srn_format.write_mask(white / "mask" / png.name, np.zeros((16, 16), dtype=bool))
    weights = save_tiny(tmp / "tiny.safetensors", tiny_config("cars", "none", resolution=16), seed=3)
    args = ["eval", "--checkpoint", weights, "--data", root, "--views-stride", "13", "--no-mesh", "--save-renders",
            "--no-progress"]
    return {"tmp": tmp, "root": root, "args": args}


def _eval(case, name: str, *extra) -> tuple[dict, list[dict], Path]:
    out = case["tmp"] / name
    assert cli(*case["args"], "--out", out, *extra) == 0
    with open(out / "renders.csv", newline="") as f:
        renders = list(csv.DictReader(f))
    return json.loads((out / "summary.json").read_text()), renders, out


def test_defaults_are_pixelnerfs_and_the_white_car_is_left_out(case):
    assert ProtocolChoices().is_pixelnerf and WHITE_CAR in PIXELNERF_UNLOADABLE
    summary, _, out = _eval(case, "default")
    choices = summary["protocol_choices"]
    assert (choices["ssim"], choices["scored"], choices["objects"]) == ("uniform7", "png8", "pixelnerf")
    assert choices["pixelnerf_defaults"] and choices["skipped_objects"] == [WHITE_CAR]
    assert choices["ssim_window"] == SSIM_WINDOWS["uniform7"]
    assert summary["metrics_path"] == "quantized 8-bit renders (calc_metrics.py)"
    assert summary["objects"] == 2 and WHITE_CAR not in {o["object_id"] for o in summary["per_object"]}
    assert f"2 of 3 objects of cars_test ({WHITE_CAR} left out: pixelNeRF cannot load it)" in summary["protocol"]
    assert not (out / "renders" / WHITE_CAR).exists()
    kept, _, _ = _eval(case, "all", "--objects", "all")
    assert kept["objects"] == 3 and kept["protocol_choices"]["skipped_objects"] == []
    assert WHITE_CAR in {o["object_id"] for o in kept["per_object"]} and "left out" not in kept["protocol"]
    same = {o["object_id"]: o["psnr"] for o in summary["per_object"]}
    assert all(o["psnr"] == same[o["object_id"]] for o in kept["per_object"] if o["object_id"] != WHITE_CAR)


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return 10 * math.log10(1 / max(float(np.mean((a - b) ** 2)), 1e-10))


def test_png8_scores_the_png_on_disk_exactly_with_each_ssim(case):
    """Native resolution: ``gt_path`` is the dataset's PNG and (png8) the render PNG is the scored image, so the
    textbook PSNR and the brute-force Gaussian SSIM of the two files give renders.csv's numbers (up to the
    float32 rounding of k/255 in the image readers: 1e-6)."""
    summary, renders, out = _eval(case, "gauss", "--ssim", "gaussian11")
    assert summary["protocol_choices"]["ssim"] == "gaussian11" and len(renders) == 2 * 5
    for row in renders:
        pred = srn_format.read_rgb(out / row["render_path"]).astype(np.float64)
        gt = srn_format.read_rgb(row["gt_path"]).astype(np.float64)
        assert float(row["psnr"]) == pytest.approx(_psnr(pred, gt), abs=1e-6)
        assert float(row["ssim"]) == pytest.approx(_gaussian_ssim_reference(pred, gt, zero_pad=False), abs=1e-6)
    padded, renders_padded, _ = _eval(case, "gauss_pad", "--ssim", "gaussian11-zeropad")
    assert padded["psnr"] == summary["psnr"] and padded["ssim"] != summary["ssim"]
    for row in renders_padded[:3]:
        pred = srn_format.read_rgb(out / row["render_path"]).astype(np.float64)
        gt = srn_format.read_rgb(row["gt_path"]).astype(np.float64)
        assert float(row["ssim"]) == pytest.approx(_gaussian_ssim_reference(pred, gt, zero_pad=True), abs=1e-6)


def test_float_scoring_differs_from_the_png_by_quantisation_only(case):
    png8, renders8, _ = _eval(case, "png8_again", "--quantize")  # --quantize is --scored png8, the default
    flt, renders_f, out = _eval(case, "float", "--scored", "float")
    assert flt["protocol_choices"]["scored"] == "float" and flt["metrics_path"] == "float renders (eval.py)"
    assert png8["protocol_choices"]["scored"] == "png8" and png8["psnr"] != flt["psnr"]
    for r8, rf in zip(renders8, renders_f, strict=True):
        pred = srn_format.read_rgb(out / rf["render_path"]).astype(np.float64)  # rounded 8-bit copy
        gt = srn_format.read_rgb(rf["gt_path"]).astype(np.float64)
        rms = math.sqrt(10 ** (-float(rf["psnr"]) / 10))
        assert abs(math.sqrt(np.mean((pred - gt) ** 2)) - rms) <= 0.5 / 255 + 1e-9
        assert abs(math.sqrt(10 ** (-float(r8["psnr"]) / 10)) - rms) <= 1 / 255 + 1e-9  # truncation: < 1 step


@pytest.mark.parametrize("extra, text", [
    (["--quantize", "--scored", "float"], "--quantize (= --scored png8) contradicts --scored float"),
    (["--ssim", "gaussian11", "--resolution", "8"], "--resolution must be >= 11 (SSIM gaussian11), got 8"),
])
def test_contradicting_choices_are_one_line_errors(case, capsys, extra, text):
    assert cli(*case["args"], "--out", case["tmp"] / "bad", *extra) == 2
    err = capsys.readouterr().err
    assert text in err and err.count("\n") == 1


def test_flag_choices_match_the_registries():
    import argparse

    from depthnerf.commands import evaluate
    from depthnerf.eval.config import OBJECTS, SCORED

    parser = argparse.ArgumentParser()
    evaluate.add_arguments(parser)
    flags = {a.dest: a.choices for a in parser._actions if a.dest in ("ssim", "scored", "objects")}
    assert list(flags["ssim"]) == list(SSIM_WINDOWS) and list(flags["scored"]) == list(SCORED)
    assert list(flags["objects"]) == list(OBJECTS)


def test_default_scores_are_scikit_images_on_the_files(case):
    """With the defaults (uniform7, png8) every renders.csv score is scikit-image's own PSNR and SSIM (its current
    ``structural_similarity`` defaults are the old ``compare_ssim`` ones pixelNeRF called: 7x7 uniform window,
    sample covariance, per channel) of the render PNG and the dataset PNG, and the summary is the mean over objects
    of the per-object means of those."""
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity

    summary, renders, out = _eval(case, "skimage")
    per_object: dict[str, list[tuple[float, float]]] = {}
    for row in renders:
        pred = srn_format.read_rgb(out / row["render_path"]).astype(np.float64)
        gt = srn_format.read_rgb(row["gt_path"]).astype(np.float64)
        ref = (peak_signal_noise_ratio(gt, pred, data_range=1.0),
               structural_similarity(pred, gt, data_range=1.0, channel_axis=-1))
        assert (float(row["psnr"]), float(row["ssim"])) == pytest.approx(ref, abs=1e-6)
        per_object.setdefault(row["object_id"], []).append(ref)
    means = [np.mean(v, axis=0) for v in per_object.values()]
    assert summary["psnr"] == pytest.approx(np.mean([m[0] for m in means]), abs=1e-6)
    assert summary["ssim"] == pytest.approx(np.mean([m[1] for m in means]), abs=1e-6)
