"""Smoke runs of the benchmarks and scripts no other test runs, so that one broken by a change elsewhere fails here
instead of on its next manual use: each runs as a subprocess (one thread) on tiny inputs and must exit 0 and print
its key line; a few small scripts run their ``main()`` in this process, where starting Python would cost more than
their work. The sizes only reach the code paths; no figure is checked.

Left out, and why: ``benchmarks/bench_gather.py`` (a CUDA comparison), ``scripts/make_app_examples.py`` and the
study shell scripts other than ``gpu_compile_train.sh`` (minutes of synthesis, training or evaluation even at their
smallest), and ``benchmarks/bench_depth.py`` (a fixed 3 s timing loop; the estimators it times are tested
elsewhere)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tarfile
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh
from fixtures_checkpoints import save_tiny, tiny_config, tiny_run
from fixtures_scripts import load_script
from fixtures_srn import make_srn_fixture
from PIL import Image
from test_bench_guided import tiny_checkpoint

from depthnerf.data.srn import index_split
from depthnerf.data.synth.framing import FRAMINGS

ROOT = Path(__file__).resolve().parent.parent


def run_script(script: str, *args: object) -> subprocess.CompletedProcess:
    """``python <script> args`` from the repository root on one thread; asserts it exits 0."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, str(ROOT / script), *map(str, args)], capture_output=True,
                          text=True, env=env, cwd=ROOT, timeout=300)
    assert proc.returncode == 0, (f"{script} exited {proc.returncode}:\n{proc.stdout[-1500:]}\n"
                                  f"{proc.stderr[-3000:]}")
    return proc


def run_main(monkeypatch, capsys, name: str, *args: object) -> tuple[object, str]:
    """``scripts/<name>.py``'s ``main()`` in this process with ``args`` as its command line: its return value
    and what it printed."""
    module = load_script(name)
    monkeypatch.setattr(sys, "argv", [f"{name}.py", *map(str, args)])
    capsys.readouterr()
    return module.main(), capsys.readouterr().out


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> dict[str, Path]:
    """Two 16 px test objects of 66 views (input view 64) with depth, masks and meshes, a random depth-aware
    checkpoint (oracle prior) and a random baseline one."""
    tmp = tmp_path_factory.mktemp("smoke")
    data = make_srn_fixture(tmp / "data", "cars", {"test": 2}, views=66, size=16, with_depth=True,
                            with_mask=True, with_mesh=True)
    return {"tmp": tmp, "data": data, "depth": tiny_checkpoint(tmp / "depth.safetensors"),
            "plain": save_tiny(tmp / "plain.safetensors", tiny_config("cars", "none"))}


def coloured_box() -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=(0.4, 0.2, 0.1))
    box.visual.vertex_colors = np.tile([200, 40, 40, 255], (len(box.vertices), 1))
    return box


def empty_mesh() -> trimesh.Trimesh:
    """What ``depthnerf eval`` writes for an object with no surface."""
    return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=int))


def test_checkpoint_framing_prints_the_shipped_models_framing(monkeypatch, capsys):
    code, out = run_main(monkeypatch, capsys, "checkpoint_framing", "cpu-cars-depth")
    assert code == 0 and out.strip() in FRAMINGS


def test_synth_contact_sheet(tiny, monkeypatch, capsys):
    sheet = tiny["tmp"] / "sheet.png"
    _, out = run_main(monkeypatch, capsys, "synth_contact_sheet", tiny["data"] / "cars_test", "--view", "64",
                      "--depth", "--out", sheet)
    width, height = Image.open(sheet).size
    assert out.strip() == f"wrote {sheet} ({width}x{height})" and height == 2 * 16  # RGB tiles over depth


def test_bench_mesh():
    proc = run_script("benchmarks/bench_mesh.py", "--resolution", "16", "--repeats", "1", "--points", "500")
    assert "geometry_metrics (500 points per mesh)" in proc.stdout


def test_bench_eval():
    proc = run_script("benchmarks/bench_eval.py", "--views", "1", "--resolution", "8", "--mesh-resolution",
                      "8", "--threads", "1")
    assert "render 1 views" in proc.stdout and "total for one object" in proc.stdout


def test_bench_synth():
    proc = run_script("benchmarks/bench_synth.py", "--category", "cars", "--objects", "1", "--workers", "1",
                      "--resolution", "16", "--breakdown-objects", "1")
    assert "[breakdown, 1 process" in proc.stdout and "[end to end, 1 workers" in proc.stdout


def test_bench_model():
    proc = run_script("benchmarks/bench_model.py", "--setting", "cpu-64-r18", "--cases", "view", "--threads",
                      "1", "--repeat", "1", "--view-sizes", "8")
    assert "view  8x8 fp32" in proc.stdout and "[view: peak RSS" in proc.stdout


def test_bench_point_chunk(tiny):
    proc = run_script("benchmarks/bench_point_chunk.py", "--checkpoint", tiny["plain"], "--chunks", "4096",
                      "--rounds", "1", "--views", "1", "--mesh-resolution", "8")
    assert "point chunk   4096:" in proc.stdout


def test_bench_api_vs_cli(tiny):
    """The ``api`` case (its script is a string no linter reads); ``cli`` would cost another process."""
    proc = run_script("benchmarks/bench_api_vs_cli.py", "--checkpoint", tiny["plain"], "--views", "1",
                      "--mesh-resolution", "8", "--threads", "1", "--cases", "api")
    assert any(line.startswith("api ") and "reconstruct" in line for line in proc.stdout.splitlines())


def test_floater_probe(tiny):
    out = tiny["tmp"] / "floaters.json"
    proc = run_script("scripts/floater_probe.py", "--checkpoint", tiny["depth"], "--data", tiny["data"],
                      "--objects", "1", "--stride", "65", "--mesh-resolution", "8", "--json", out)
    assert "| as-trained |" in proc.stdout and "| no-mask-prior |" in proc.stdout
    result = json.loads(out.read_text())
    assert result["objects"] == 1 and len(result["means"]) == 5


def test_input_view_colour(tiny):
    out, figure = tiny["tmp"] / "input_colour.json", tiny["tmp"] / "input_colour.png"
    proc = run_script("scripts/input_view_colour.py", "--checkpoint", tiny["plain"], "--data", tiny["data"],
                      "--objects", "1", "--nearest", "3", "--every", "1", "--bins", "0", "0.5", "180",
                      "--surface", "--figure", figure, "--json", out)
    assert f"| {tiny['plain']} | 0-0.5 | 1 |" in proc.stdout and "at the input view's true surface" in proc.stdout
    result = json.loads(out.read_text())[str(tiny["plain"])]
    views = result["views"]
    assert views[0]["view"] == 64 and views[0]["angle"] < 0.5
    assert result["surface"]["objects"] == 1 and result["surface"]["field_delta_ab"] >= 0
    assert np.asarray(Image.open(figure)).shape == (48, 144, 3)  # truth | render | difference, 16 px x 3
    run_script("scripts/input_view_colour.py", "--checkpoint", tiny["plain"], tiny["depth"], "--data", tiny["data"],
               "--objects", "2", "--nearest", "1", "--figure", figure, "--figure-objects", "2")
    assert np.asarray(Image.open(figure)).shape == (96, 144, 3)  # truth | each checkpoint's render, two objects


def test_colour_probe(tiny):
    data = make_srn_fixture(tiny["tmp"] / "probe", "cars", {"train": 3, "test": 1}, views=66, size=16,
                            with_mask=True)
    out = tiny["tmp"] / "probe.json"
    proc = run_script("scripts/colour_probe.py", "--checkpoint", tiny["plain"], "--data", data, "--fit-objects", "3",
                      "--encoder-norm", "running", "image", "--json", out)
    assert "| running |" in proc.stdout and "| image |" in proc.stdout
    result = json.loads(out.read_text())
    assert len(result["image"]["r2"]) == 3 and result["running"]["test_pixels"] > 0


def test_mesh_components_of_a_mesh_and_an_empty_one(tiny):
    run = tiny_run(tiny["tmp"] / "runs" / "tiny", tiny_config("cars", "none"))
    meshes = tiny["tmp"] / "eval" / "tiny" / "meshes"  # the default --eval-root: RUN/../../eval
    meshes.mkdir(parents=True)
    first, second = (r.object_id for r in index_split(tiny["data"], "cars", "test").objects)
    coloured_box().export(meshes / f"{first}.ply")
    empty_mesh().export(meshes / f"{second}.ply")
    proc = run_script("scripts/mesh_components.py", run, "--data", tiny["data"], "--objects", "2")
    assert f"tiny {first}: 1 components; 8 verts at" in proc.stdout
    assert f"tiny {second}: 0 components" in proc.stdout


def test_render_meshes(tiny, capsys):
    pytest.importorskip("matplotlib", reason="matplotlib is not installed (pip install -e '.[figures]')")
    box, empty, out = tiny["tmp"] / "box.ply", tiny["tmp"] / "empty.ply", tiny["tmp"] / "meshes.png"
    coloured_box().export(box)
    proc = run_script("scripts/render_meshes.py", box, "--labels", "box", "--out", out)
    assert f"wrote {out}" in proc.stdout and out.is_file()
    empty_mesh().export(empty)
    assert load_script("render_meshes").main([str(empty), "--out", str(tiny["tmp"] / "none.png")]) == 2
    assert capsys.readouterr().err.strip() == f"error: {empty}: empty mesh (no faces)"


def test_measure_fill(monkeypatch, capsys):
    """Its ``depthnerf synth`` calls run in this process too (four more processes would cost more than the
    rest of this file); one 16 px object per framing and category."""
    from depthnerf.cli import main as cli_main

    fill = load_script("measure_fill")

    def synth(cmd: list[str], check: bool) -> None:
        assert cmd[1:4] == ["-m", "depthnerf", "synth"] and check
        assert cli_main(cmd[3:]) == 0

    monkeypatch.setattr(fill, "subprocess", SimpleNamespace(run=synth))
    monkeypatch.setattr(sys, "argv", ["measure_fill.py", "--objects", "1", "--resolution", "16"])
    assert fill.main() == 0
    lines = [line for line in capsys.readouterr().out.splitlines() if "median fill" in line]
    assert len(lines) == 2 * len(FRAMINGS)
    table = FRAMINGS["srn"].fill("cars", float("nan"))
    assert any(line.startswith("srn     cars") and line.endswith(f"Framing.fill: {table}") for line in lines)


def test_facing_study_side_preference(tiny, monkeypatch, capsys):
    """``--side-tolerance``: the ``prefer`` column is the side plane's PSNR exactly where the side plane's
    input-view error is within ``1 + tolerance`` of ``auto``'s choice, else ``auto``'s; a huge tolerance always
    prefers it. In this process: a subprocess per tolerance would cost more than the renders."""
    from depthnerf.config_io import apply_overrides

    mirror = save_tiny(tiny["tmp"] / "mirror.safetensors",
                       apply_overrides(tiny_config("cars", "none"), ["--model.mirror", "true"]))
    common = ["--checkpoint", mirror, "--data", tiny["data"], "--category", "cars", "--objects", "2",
              "--input-views", "64", "--views-stride", "65"]
    for tolerance in ("0", "1e9"):
        out = tiny["tmp"] / f"facing-{tolerance}.json"
        code, printed = run_main(monkeypatch, capsys, "facing_study", *common, "--side-tolerance", tolerance,
                                 "--json", out)
        assert code == 0 and f"tolerance {float(tolerance):g}) against auto" in printed
        for case in json.loads(out.read_text()):
            fit = case["fit"]
            chosen = fit["none_error"] if fit["facing"] is None else fit["error"]
            assert case["prefer_side"] == (case["side_error"] <= (1 + float(tolerance)) * chosen)
            assert case["psnr"]["prefer"] == case["psnr"]["side" if case["prefer_side"] else "auto"]
            assert case["prefer_side"] or tolerance == "0"
    monkeypatch.setattr(sys, "argv", ["facing_study.py", *map(str, common), "--side-tolerance", "-1"])
    assert load_script("facing_study").main() == 2
    assert "--side-tolerance must be >= 0, got -1.0" in capsys.readouterr().err


def test_bench_loader(tmp_path):
    data = make_srn_fixture(tmp_path / "data", "cars", {"train": 2}, views=5, size=16, with_mask=True)
    out = tmp_path / "loader.json"
    proc = run_script("benchmarks/bench_loader.py", "--data", data, "--resolution", 16, "--steps", 2, "--workers", 1,
                      "--json", out)
    assert "view store: built in" in proc.stdout
    paths = json.loads(out.read_text())["paths"]
    assert set(paths) == {"files", "view_store"} and "loader_ms_per_step_1_workers" in paths["view_store"]


def test_gpu_compile_train_script_on_the_cpu(tmp_path):
    """The lease script's store run, shrunk to the CPU: it trains, and its JSON has the run's figures."""
    tiny = ("--model.encoder.backbone resnet18 --model.coarse.d_hidden 16 --model.fine.d_hidden 16 "
            "--render.sampler.n_coarse 4 --render.sampler.n_importance 2 --render.sampler.n_gaussian 2 "
            "--schedule.objects_phase1 2 --schedule.objects_phase2 4 --schedule.bbox_steps 3 "
            "--schedule.rays_per_object 16")
    env = {**os.environ, "OMP_NUM_THREADS": "1", "WORK": str(tmp_path / "work"), "RUNS": "eager-store",
           "DEVICE": "cpu", "RES": "32", "VIEWS": "3", "STEPS": "4", "WORKERS": "0", "SECONDS_EACH": "200",
           "TRAIN_ARGS": tiny}
    proc = subprocess.run(["bash", str(ROOT / "scripts" / "gpu_compile_train.sh"), str(tmp_path / "out")],
                          capture_output=True, text=True, env=env, cwd=ROOT, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    run = json.loads((tmp_path / "out" / "compile_train.json").read_text())["eager-store"]
    assert run["rc_wall"][1] == "rc=0" and run["last_step"] == 4
    logged = [json.loads(line) for line in (tmp_path / "work" / "runs" / "eager-store" / "metrics.jsonl")
              .read_text().splitlines()]
    logged = [m for m in logged if "loss" in m]
    # steps 1-3 ran phase 1 (2 objects x 16 rays), step 4 phase 2 (4 x 16); the JSON's median is over steps 3-4
    ms = [1e3 * (2 if m["step"] <= 3 else 4) * 16 / m["rays_per_s"] for m in logged]
    assert run["ms_per_step"] == pytest.approx(float(np.median(ms[2:])), rel=1e-9)
    assert "view store " in (tmp_path / "out" / "compile_train_logs.txt").read_text()


def test_gpu_checkpoint_script_on_the_cpu(tmp_path):
    """The lease script that trains a checkpoint to ship, shrunk to the CPU and to two calls of ~60 s (the first
    leaves the main run ~15 s after data, priors and probe on a busy machine, e.g. beside another test
    worker): the probe is stopped by its time limit and checkpoints, the main run starts from its weights with
    the planned cosine schedule, is stopped by the first call's share and finished by the second (CONTINUE=1),
    and the archive holds what evaluation and export read, without optimiser states."""
    tiny = ("--model.encoder.backbone resnet18 --model.coarse.d_hidden 16 --model.fine.d_hidden 16 "
            "--render.sampler.n_coarse 4 --render.sampler.n_importance 2 --render.sampler.n_gaussian 2 "
            "--schedule.objects_phase1 2 --schedule.objects_phase2 2 --schedule.bbox_steps 3 "
            "--schedule.rays_per_object 16 --log.log_every 1")
    env = {**os.environ, "OMP_NUM_THREADS": "1", "WORK": str(tmp_path / "work"), "DEVICE": "cpu", "RES": "32",
           "TRAIN_OBJECTS": "2", "VIEWS": "3", "SYNTH_WORKERS": "1", "DATA_WORKERS": "0", "SECONDS_TOTAL": "85",
           "CALL_SECONDS": "60", "PROBE_SECONDS": "14", "RESERVE_S": "2", "START_S": "6", "TRAIN_ARGS": tiny,
           "EVAL_OBJECTS": "2", "EVAL_ARGS": "--mesh-resolution 16 --mesh-points 500"}
    out, script = tmp_path / "out", ["bash", str(ROOT / "scripts" / "gpu_checkpoint.sh")]
    refused = subprocess.run([*script, str(out)], capture_output=True, text=True, env={**env, "CONTINUE": "1"},
                             cwd=ROOT, timeout=300)
    assert refused.returncode == 2 and "plan.txt is missing" in refused.stderr
    proc = subprocess.run([*script, str(out)], capture_output=True, text=True, env=env, cwd=ROOT, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    first = json.loads((out / "gpu_checkpoint.json").read_text())
    assert first["stages"]["main"]["rc"] == 124
    assert 0 < first["runs"]["main"]["last_step"] < first["main_steps_planned"]
    probe_log = (out / "gpu_checkpoint_log.txt").read_text().split("== probe")[1]
    assert "0 objects decoded, 0 changed since and decoded again, 2 reused" in probe_log  # the store stage made them
    assert not (out / "eval_main_summary.json").exists() and first["eval"] == {}  # no time left for it
    # the second call scores the main run beside the first call's last checkpoint, given as INIT
    init = tmp_path / "first"
    shutil.copytree(tmp_path / "work" / "runs" / "main" / "checkpoints" / first["runs"]["main"]["checkpoint"], init)
    proc = subprocess.run([*script, str(out)], capture_output=True, text=True, cwd=ROOT, timeout=300,
                          env={**env, "CONTINUE": "1", "CALL_SECONDS": "150", "INIT": str(init)})
    assert proc.returncode == 0, proc.stderr[-2000:]
    second_log = (out / "gpu_checkpoint_log.txt").read_text()
    assert "continuing the main run (planned: " in second_log and "== data" not in second_log
    assert f"resumed from step {first['runs']['main']['checkpoint'].split('_')[-1].lstrip('0')} (" in second_log
    res = json.loads((out / "gpu_checkpoint.json").read_text())
    assert res["stages"]["main"]["rc"] == 0 and res["main_steps_planned"] == first["main_steps_planned"]
    assert res["stages"]["eval-main"]["rc"] == 0 and res["stages"]["eval-init"]["rc"] == 0
    summary = json.loads((out / "eval_main_summary.json").read_text())
    assert summary["objects"] == 2 and summary["views_stride"] == 25 and res["eval"]["main"]["psnr"] == summary["psnr"]
    assert res["eval"]["init"]["objects"] == 2 and "| psnr | 2 |" in (out / "eval_paired.md").read_text()
    assert res["runs"]["main"]["last_step"] == res["main_steps_planned"]
    assert all(res["stages"][name]["rc"] == 0 for name in ("data", "priors", "store"))
    assert res["stages"]["probe"]["rc"] == 124 and res["runs"]["probe"]["last_step"] > 3  # stopped by its limit
    assert res["probe_ms_per_step"] > 0 and res["main_steps_planned"] > 0 and res["runs"]["main"]["last_step"] > 0
    with tarfile.open(out / "run.tar.gz") as tar:
        tar.extractall(tmp_path / "unpacked", filter="data")
    main = tmp_path / "unpacked" / "main"
    cfg = json.loads((main / "config.json").read_text())
    assert cfg["schedule"]["lr_schedule"] == "cosine" and cfg["schedule"]["max_steps"] == res["main_steps_planned"]
    assert cfg["model"]["mirror"] and cfg["model"]["prior_at_point"]
    latest = (main / "checkpoints" / "latest").read_text().strip()
    assert latest == res["runs"]["main"]["checkpoint"]
    assert [p.name for p in (main / "checkpoints").iterdir() if p.is_dir()] == [latest]
    assert sorted(p.name for p in (main / "checkpoints" / latest).iterdir()) == ["model.safetensors", "state.json"]
    assert "probe" in json.loads((main / "init_from.json").read_text())["source"]
    assert not list((tmp_path / "unpacked").rglob("optimizer.safetensors"))
