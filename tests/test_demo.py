"""``depthnerf demo`` end to end on tiny random checkpoints (16 px, 5 scored views, 3 turntable frames).

Checked against ground truth: the reported PSNR/SSIM against metrics recomputed from the saved PNG pairs (and
PSNR against scikit-image's own function), the saved true views against the synthesised dataset's files, the
input against view 64, the depth-prior image against the input mask, the object's seed, and the error paths.
"""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
from fixtures_checkpoints import save_tiny, tiny_bundled, tiny_config
from PIL import Image
from skimage.metrics import peak_signal_noise_ratio

from depthnerf.cli import main
from depthnerf.data import srn_format
from depthnerf.demo import DEMO_SEED
from depthnerf.eval.metrics import psnr, ssim

ARGS = ["--views-stride", "50", "--turntable-views", "3", "--mesh-resolution", "12", "--no-progress"]


@pytest.fixture(scope="module")
def demo(tmp_path_factory) -> tuple[Path, dict, str]:
    tmp = tmp_path_factory.mktemp("demo")
    weights = tiny_bundled(tmp / "bundled.safetensors")
    cars = save_tiny(tmp / "cars.safetensors", tiny_config("cars", "bundled", weights))
    chairs = save_tiny(tmp / "chairs.safetensors", tiny_config("chairs", "oracle"), seed=1)
    out = tmp / "out"
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = main(["demo", "--out", str(out), "--cars-checkpoint", str(cars), "--chairs-checkpoint", str(chairs),
                     *ARGS])
    assert code == 0
    return out, json.loads((out / "demo.json").read_text()), buf.getvalue()


def _read(path: Path) -> np.ndarray:
    return srn_format.read_rgb(path).astype(np.float64)


@pytest.mark.parametrize("category", ["cars", "chairs"])
def test_files_and_data(demo, category):
    out, summary, _ = demo
    r = summary["categories"][category]
    folder = out / category
    for name in ("input.png", "depth_prior.png", "novel_views.png", "turntable.gif", "mesh.ply", "manifest.json"):
        assert (folder / name).is_file(), name
    assert len(iio.imread(folder / "turntable.gif")) == 3
    assert r["input_view"] == 64 and r["target_views"] == [0, 50, 101, 151, 201]
    obj = out / "data" / f"{category}_test" / r["object_id"]
    assert len(list((obj / "rgb").glob("*.png"))) == 251 and (obj / "mesh.ply").is_file()
    card = json.loads((out / "data" / f"{category}_card.json").read_text())
    assert card["seed"] == DEMO_SEED != 0 and card["counts"] == {"train": 0, "val": 0, "test": 1}
    assert card["resolution"] == 16
    # the input is the dataset's view 64; the depth prior covers exactly the input mask
    assert np.array_equal(_read(folder / "input.png"), _read(obj / "rgb" / "000064.png"))
    mask = np.asarray(Image.open(folder / "input_mask.png")) > 0
    prior = np.asarray(Image.open(folder / "depth_prior.png"))
    assert mask.any() and np.array_equal(prior > 0, mask)
    strip = np.asarray(Image.open(folder / "novel_views.png"))
    assert strip.shape == (2 * 16 + 2, 5 * 16 + 4 * 2, 3)
    assert r["files"]["novel_views"]["strip"] == f"{category}/novel_views.png"


@pytest.mark.parametrize("category", ["cars", "chairs"])
def test_metrics_match_saved_pngs(demo, category):
    out, summary, _ = demo
    r = summary["categories"][category]
    obj = out / "data" / f"{category}_test" / r["object_id"]
    files = r["files"]["novel_views"]
    psnrs, ssims = [], []
    for view, pred_rel, true_rel in zip(r["target_views"], files["pred"], files["true"], strict=True):
        pred, true = _read(out / pred_rel), _read(out / true_rel)
        assert np.array_equal(true, _read(obj / "rgb" / f"{view:06d}.png"))  # the truth is the dataset's view
        assert not np.array_equal(pred, true)
        psnrs.append(psnr(pred, true))
        ssims.append(ssim(pred, true))
        assert psnrs[-1] == pytest.approx(peak_signal_noise_ratio(true, pred, data_range=1.0), abs=1e-9)
    assert [v["view"] for v in r["per_view"]] == r["target_views"]
    # saved renders are 8-bit: the float-render metrics differ by at most the quantisation
    assert r["psnr"] == pytest.approx(float(np.mean(psnrs)), abs=0.02)
    assert r["ssim"] == pytest.approx(float(np.mean(ssims)), abs=0.01)
    assert r["psnr"] == pytest.approx(np.mean([v["psnr"] for v in r["per_view"]]), abs=1e-9)


def test_summary_and_printout(demo):
    out, summary, printed = demo
    assert list(summary["categories"]) == ["cars", "chairs"]
    cars, chairs = summary["categories"]["cars"], summary["categories"]["chairs"]
    assert cars["depth_prior"] == "bundled" and chairs["depth_prior"] == "oracle"
    assert any("oracle" in n and "ground-truth" in n for n in chairs["notes"])
    assert len(cars["checkpoint_sha256"]) == 64 and cars["checkpoint_sha256"] != chairs["checkpoint_sha256"]
    assert summary["seconds"] > 0 and cars["seconds"]["total_s"] > 0
    for r in summary["categories"].values():
        assert f"{r['psnr']:.2f}" in printed and f"{r['ssim']:.3f}" in printed
    assert "demo wall time:" in printed and str(out / "demo.json") in printed


def test_missing_checkpoint_is_one_line_exit_2(tmp_path, capsys):
    out = tmp_path / "out"
    code = main(["demo", "--out", str(out), "--cars-checkpoint", "cpu-cars-missing", "--categories", "cars", *ARGS])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1 and err.startswith("error: ")
    assert "cpu-cars-missing" in err and "depthnerf checkpoints" in err
    assert not out.exists()  # fails before any work


def test_wrong_category_checkpoint(tmp_path, capsys):
    chairs = save_tiny(tmp_path / "chairs.safetensors", tiny_config("chairs", "none"))
    code = main(["demo", "--out", str(tmp_path / "out"), "--cars-checkpoint", str(chairs), "--categories", "cars"])
    assert code == 2 and "trained on chairs" in capsys.readouterr().err


def test_a_rerun_into_the_same_out_repeats_its_scores_and_leaves_no_stale_views(demo, tmp_path):
    """``--out`` reused: the same flags give the same PSNR/SSIM (deterministic sampling, same object), and a run
    with another ``--views-stride`` or ``--seed`` leaves exactly its own novel views in ``novel_views/``."""
    cars = demo[0].parent / "cars.safetensors"
    out = tmp_path / "out"

    def run(*flags: str) -> dict:
        with contextlib.redirect_stdout(io.StringIO()):
            assert main(["demo", "--out", str(out), "--cars-checkpoint", str(cars), "--categories", "cars",
                         "--turntable-views", "1", "--mesh-resolution", "8", "--no-progress", *flags]) == 0
        return json.loads((out / "demo.json").read_text())["categories"]["cars"]

    first, again = run("--views-stride", "50"), run("--views-stride", "50")
    assert (again["psnr"], again["ssim"], again["per_view"]) == (first["psnr"], first["ssim"], first["per_view"])
    for flags in (["--views-stride", "125"], ["--views-stride", "125", "--seed", "5"]):
        r = run(*flags)
        listed = {Path(p).name for kind in ("pred", "true") for p in r["files"]["novel_views"][kind]}
        assert {p.name for p in (out / "cars" / "novel_views").iterdir()} == listed, flags
        assert len(listed) == 2 * len(r["target_views"]) == 2 * 2
