"""The study figure scripts: ``scripts/plot_training_curves.py`` and ``scripts/qualitative_figure.py``.

Training curves: fake run folders whose ``metrics.jsonl`` is written by the project's own
:class:`~depthnerf.train.run_log.RunLog` with known values; the figure's CSV must give back exactly those values
(and the moving average computed here independently). Qualitative figure: three tiny real runs (baseline,
``bundled`` with random tiny weights, ``oracle``) trained one step and evaluated by the real ``depthnerf eval
--save-renders`` on a fixture whose test objects have 66 views (input view 64); the CSV must copy renders.csv's
PSNR, and the oracle prior must be ``1/z`` of the fixture's depth map.
"""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from fixtures_scripts import load_script
from fixtures_srn import make_srn_fixture
from PIL import Image

from depthnerf.cli import main as cli_main
from depthnerf.config_io import to_dict
from depthnerf.data import srn_format
from depthnerf.data.srn import index_split
from depthnerf.depth.bundled import BundledDepthNet, BundledNetConfig, save_bundled
from depthnerf.errors import DepthnerfError
from depthnerf.files import sha256_files
from depthnerf.train.config import preset, with_prior
from depthnerf.train.run_log import RunLog

TINY = ["--max-steps", "1", "--log.val_every", "0", "--data.resolution", "32", "--data.num_workers", "0",
        "--model.coarse.d_hidden", "16", "--model.fine.d_hidden", "16", "--model.encoder.backbone", "resnet18",
        "--schedule.objects_phase1", "1", "--schedule.rays_per_object", "16", "--render.sampler.n_coarse", "8",
        "--render.sampler.n_importance", "4", "--render.sampler.n_gaussian", "2", "--no-progress"]
"""Training flags of the tiny models."""


curves_script = load_script("plot_training_curves")
qual_script = load_script("qualitative_figure")


def read_csv(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def check_png(path: Path, min_width: int, min_height: int) -> None:
    with Image.open(path) as im:
        assert im.format == "PNG" and im.width >= min_width and im.height >= min_height
        pixels = np.asarray(im.convert("RGB"))
    assert pixels.std() > 5  # something was drawn


def fake_run(root: Path, category: str, prior: str, losses: dict[int, float], vals: dict[int, float]) -> Path:
    """A run folder with the real config.json and a metrics.jsonl written by RunLog."""
    run = root / f"{category}-{prior}"
    run.mkdir(parents=True)
    cfg = with_prior(preset(f"cpu-{category}"), prior)
    (run / "config.json").write_text(json.dumps(to_dict(cfg), indent=1) + "\n")
    log = RunLog(run, 0, tensorboard=False)
    for step in sorted(set(losses) | set(vals)):
        if step in losses:
            log.log(step, {"loss": losses[step], "lr": 3e-4, "psnr_train": 10.0})
        if step in vals:
            log.log(step, {"val_psnr": vals[step], "val_ssim": 0.5}, prefix="val")
    log.close()
    return run


def test_training_curves_csv_holds_the_logged_numbers(tmp_path):
    rng = np.random.default_rng(0)
    inputs = {}
    for k, (category, prior) in enumerate([("cars", "none"), ("cars", "bundled"), ("chairs", "none"),
                                           ("chairs", "oracle")]):
        losses = {s: float(rng.uniform(0.01, 0.1)) for s in range(25, 301, 25)}
        vals = {s: float(12 + k + s / 100 + rng.uniform()) for s in (100, 200, 300)}
        if prior == "oracle":
            losses[150] = float("nan")  # logged as null: left out of the plot
        inputs[(category, prior)] = (fake_run(tmp_path, category, prior, losses, vals), losses, vals)
    with open(inputs[("chairs", "oracle")][0] / "metrics.jsonl", "a") as f:
        f.write('{"step": 325, "lo')  # a live run's line being written: ignored
    out = tmp_path / "fig" / "curves.png"
    runs = [str(v[0]) for v in inputs.values()]
    assert curves_script.main(["--runs", *runs, "--out", str(out), "--title", "t", "--smoothing", "0.6"]) == 0
    check_png(out, 600, 400)
    rows = read_csv(out.with_suffix(".csv"))
    for (category, prior), (run, losses, vals) in inputs.items():
        mine = [r for r in rows if r["run"] == str(run)]
        assert {r["category"] for r in mine} == {category} and {r["prior"] for r in mine} == {prior}
        label = {"none": "pixelNeRF (baseline)", "bundled": "depth-aware (bundled prior)",
                 "oracle": "depth-aware (oracle prior)"}[prior]
        assert {r["label"] for r in mine} == {label}
        got_val = {int(r["step"]): float(r["value"]) for r in mine if r["metric"] == "val_psnr"}
        assert got_val == vals  # exact: values are written with repr
        finite = {s: v for s, v in losses.items() if np.isfinite(v)}
        assert len(finite) == len(losses) - (prior == "oracle")
        got_loss = {int(r["step"]): float(r["value"]) for r in mine if r["metric"] == "loss"}
        assert got_loss == finite
        expected, mean = [], 0.0
        for k, s in enumerate(sorted(finite), start=1):
            mean = 0.6 * mean + 0.4 * finite[s]
            expected.append(mean / (1 - 0.6**k))
        smoothed = [float(r["value"]) for r in mine if r["metric"] == "loss_smoothed"]
        assert smoothed == pytest.approx(expected, rel=1e-12)
    assert smoothed[0] == finite[25]  # debiased: the first point is the first value


def test_training_curves_errors_name_the_file(tmp_path, capsys):
    run = fake_run(tmp_path, "cars", "none", {25: 0.1, 50: 0.05}, {})
    assert curves_script.main(["--runs", str(run), "--out", str(tmp_path / "f.png")]) == 2
    err = capsys.readouterr().err
    assert f"{run / 'metrics.jsonl'}: no validation records" in err and len(err.strip().splitlines()) == 1
    with pytest.raises(DepthnerfError, match="config.json: missing"):
        curves_script.read_run(tmp_path)
    (run / "metrics.jsonl").write_text('{"step": 1, "loss": 0.1}\nnot json\n{"step": 2, "val_psnr": 3.0}\n')
    with pytest.raises(DepthnerfError, match="line 2 is not valid JSON"):
        curves_script.read_run(run)


@pytest.fixture(scope="module")
def evals(tmp_path_factory) -> dict:
    """A fixture dataset, three one-step runs and their evals with --save-renders."""
    tmp = tmp_path_factory.mktemp("studyfig")
    root = tmp / "data"
    make_srn_fixture(root, "cars", {"train": 2}, views=3, size=32, with_depth=True)
    make_srn_fixture(root, "cars", {"test": 2}, views=66, size=32, with_depth=True)
    torch.manual_seed(0)
    weights = tmp / "bundled.safetensors"
    save_bundled(BundledDepthNet(BundledNetConfig(widths=(8, 8, 8), input_size=32, unshuffle=1)), weights)
    assert cli_main(["depth", "--data", str(root), "--estimator", "bundled", "--checkpoint", str(weights),
                     "--splits", "train", "test", "--no-progress"]) == 0
    out = {"root": root, "tmp": tmp}
    for prior in ("none", "bundled", "oracle"):
        extra = ["--depth-checkpoint", str(weights)] if prior == "bundled" else []
        run = tmp / f"run-{prior}"
        assert cli_main(["train", "--depth", prior, *extra, "--data", str(root), "--out", str(run), *TINY]) == 0
        out[prior] = tmp / f"eval-{prior}"
        assert cli_main(["eval", "--run", str(run), "--views-stride", "16", "--save-renders", "--no-mesh",
                         "--out", str(out[prior]), "--no-progress"]) == 0
    return out


def test_qualitative_figure_shows_inputs_priors_and_renders(evals):
    dirs = [str(evals[p]) for p in ("none", "bundled", "oracle")]
    out = evals["tmp"] / "qual.png"
    assert qual_script.main(["--evals", *dirs, "--data", str(evals["root"]), "--out", str(out),
                             "--objects", "2", "--view", "32"]) == 0
    check_png(out, 500, 300)
    rows = read_csv(out.with_suffix(".csv"))
    ids = [r.object_id for r in index_split(evals["root"], "cars", "test").objects]
    columns = ["input view", "depth prior (bundled)", "depth prior (oracle)", "ground truth",
               "pixelNeRF (baseline)", "depth-aware (bundled)", "depth-aware (oracle)"]
    assert [r["object_id"] for r in rows] == [i for i in ids for _ in columns]
    assert [r["column"] for r in rows] == columns * 2
    assert [int(r["view"]) for r in rows] == [64, 64, 64, 32, 32, 32, 32] * 2
    for prior, eval_dir in zip(("none", "bundled", "oracle"), dirs, strict=True):
        renders = {(r["object_id"], int(r["view"])): r for r in read_csv(Path(eval_dir) / "renders.csv")}
        for row in (r for r in rows if r["column"] == columns[4 + ("none", "bundled", "oracle").index(prior)]):
            expected = renders[(row["object_id"], 32)]
            assert float(row["psnr"]) == float(expected["psnr"])
            assert Path(row["source"]) == Path(eval_dir) / expected["render_path"]
    assert all(r["psnr"] == "" for r in rows if r["column"] in columns[:4])
    assert "depth_priors/bundled-" in rows[1]["source"] and rows[1]["source"].endswith(f"{ids[0]}.safetensors")

    # the oracle cell is 1/z of the fixture's depth map at the input view (ground truth, computed here)
    ev = qual_script.load_eval_dir(evals["oracle"])
    record = index_split(evals["root"], "cars", "test").objects[0]
    store = qual_script.open_prior_store(ev, evals["root"])
    depth = srn_format.read_depth(record.depth_path(64))
    expected = np.where(depth > 0, 1.0 / np.maximum(depth, 1e-12), 0.0)
    np.testing.assert_allclose(store.load(record, [64])[0].numpy(), expected, rtol=1e-5)
    colours = qual_script.colorize(expected, depth > 0)
    assert colours.shape == (32, 32, 3) and np.ptp(colours[depth == 0], axis=0).max() == 0
    assert colours[depth > 0].std(axis=0).max() > 0.1
    brightness = colours.sum(axis=-1)  # magma: brighter = larger disparity = nearer
    fg_disp = np.where(depth > 0, expected, np.inf)
    assert brightness.flat[np.argmax(expected)] > brightness.flat[np.argmin(fg_disp)] + 1.0


def test_qualitative_figure_default_view_and_errors(evals, capsys, tmp_path):
    out = tmp_path / "q.png"
    assert qual_script.main(["--evals", str(evals["none"]), str(evals["bundled"]), "--out", str(out),
                             "--objects", "1"]) == 0  # --data defaults to the summary's dataset
    rows = read_csv(out.with_suffix(".csv"))
    assert [int(r["view"]) for r in rows] == [64, 64, 0, 0, 0]  # first rendered target: view 0
    check_png(out, 300, 150)
    assert qual_script.main(["--evals", str(evals["none"]), "--out", str(out), "--view", "5"]) == 2
    assert "view 5 of" in capsys.readouterr().err
    bare = tmp_path / "bare"
    bare.mkdir()
    for name in ("summary.json", "per_object.csv"):
        (bare / name).write_bytes((evals["none"] / name).read_bytes())
    assert qual_script.main(["--evals", str(bare), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"{bare / 'renders.csv'}: missing; rerun depthnerf eval with --save-renders" in err


def test_qualitative_figure_keys_priors_by_their_weights(evals, capsys, tmp_path):
    """Two evals of the same estimator with other weights get a prior column each, named by their weights; a
    summary whose recorded weights hash the cache it names does not serve is an error."""
    torch.manual_seed(5)
    other = tmp_path / "other.safetensors"
    save_bundled(BundledDepthNet(BundledNetConfig(widths=(8, 8, 8), input_size=32, unshuffle=1)), other)
    assert cli_main(["depth", "--data", str(evals["root"]), "--depth", "bundled", "--depth-checkpoint", str(other),
                     "--splits", "test", "--no-progress"]) == 0
    second = tmp_path / "eval-other"
    shutil.copytree(evals["bundled"], second)
    summary = json.loads((second / "summary.json").read_text())
    summary["depth_prior_provenance"].update(checkpoint=str(other), weights_hash=sha256_files([other], names=False))
    (second / "summary.json").write_text(json.dumps(summary))
    out = tmp_path / "two.png"
    assert qual_script.main(["--evals", str(evals["bundled"]), str(second), "--data", str(evals["root"]),
                             "--out", str(out), "--objects", "1", "--labels", "a", "b"]) == 0
    columns = [r["column"] for r in read_csv(out.with_suffix(".csv"))]
    assert columns[:3] == ["input view", "depth prior (bundled, bundled.safetensors)",
                           "depth prior (bundled, other.safetensors)"]
    summary["depth_prior_provenance"]["weights_hash"] = "0" * 64  # names other.safetensors, records other weights
    (second / "summary.json").write_text(json.dumps(summary))
    assert qual_script.main(["--evals", str(second), "--data", str(evals["root"]), "--out", str(out)]) == 2
    assert "the eval read 'bundled' weights sha256 000000000000..." in capsys.readouterr().err
