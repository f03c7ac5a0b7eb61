"""``depthnerf eval`` (the SRN protocol driver) and ``depthnerf checkpoints``, end to end through the real CLI.

A tiny baseline and a tiny depth-aware model (random ``bundled`` depth weights) are trained for one step on a
fixture dataset whose test objects have 66 views (so view 64 is the input) plus an all-white object. Ground truth:
the protocol's view selection written out, per_object.csv recomputing the summary, renders.csv PNGs recomputing
PSNR within 8-bit quantisation, and a *constant field* checkpoint (zero output weights: every ray renders the
constant colour, every grid point has the constant density) whose PSNR and mesh have closed forms.
"""

from __future__ import annotations

import csv
import json
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from fixtures_srn import make_srn_fixture

from depthnerf.cli import main
from depthnerf.config_io import to_dict
from depthnerf.data import srn_format
from depthnerf.data.cameras import world_to_camera
from depthnerf.data.protocol import INPUT_VIEW, TWO_VIEW_INPUTS, protocol_views
from depthnerf.data.srn import index_split, load_object
from depthnerf.depth.bundled import BundledDepthNet, BundledNetConfig, save_bundled
from depthnerf.errors import DepthnerfError
from depthnerf.eval.table import load_summary, markdown_table
from depthnerf.pretrained.load import load_pretrained
from depthnerf.pretrained.spec import SPEC_KEY
from depthnerf.render.mesh import CameraGrid
from depthnerf.train import checkpoint as ckpt

TINY = ["--max-steps", "1", "--log.val_every", "0", "--data.resolution", "32", "--data.num_workers", "0",
        "--model.coarse.d_hidden", "32", "--model.fine.d_hidden", "32", "--model.encoder.backbone", "resnet18",
        "--schedule.objects_phase1", "1", "--schedule.rays_per_object", "32", "--render.sampler.n_coarse", "16",
        "--render.sampler.n_importance", "8", "--render.sampler.n_gaussian", "4", "--no-progress"]
"""Training flags of the tiny test models."""
WHITE_ID = "ffffffffffffffffffffffffffffffff"
"""The all-white test object."""
COLOR = (0.2, 0.6, 0.8)
"""Colour of the constant-field checkpoint."""


def cli(*args: str) -> int:
    return main([str(a) for a in args])


def constant_field(src: Path, dst: Path, color=COLOR, sigma: float = 1e4) -> Path:
    """A copy of checkpoint ``src`` whose coarse and fine outputs are the constant (colour, density)."""
    pre = load_pretrained(src)
    logits = [math.log(c / (1 - c)) for c in color]
    for net in (pre.model.coarse, pre.model.fine):
        net.lin_out.weight.data.zero_()
        net.lin_out.bias.data = torch.tensor([*logits, sigma])
    ckpt.save_weights(dst, pre.model, to_dict(pre.spec.model), step=pre.step, extra={SPEC_KEY: pre.spec.to_json()})
    return dst


@pytest.fixture(scope="module")
def setup(tmp_path_factory) -> dict[str, Path]:
    """Dataset (train: 2 objects x 4 views; test: 2 spheres x 66 views + an all-white object), the runs."""
    tmp = tmp_path_factory.mktemp("evalproto")
    root = tmp / "data"
    kw = {"size": 32, "with_depth": True, "with_mask": True, "with_mesh": True}
    make_srn_fixture(root, "cars", {"train": 2}, views=4, **kw)
    make_srn_fixture(root, "cars", {"test": 2}, views=66, **kw)
    first = sorted((root / "cars_test").iterdir())[0]
    white = shutil.copytree(first, root / "cars_test" / WHITE_ID)
    (white / "mesh.ply").unlink()
    for png in (white / "rgb").iterdir():
        srn_format.write_rgb(png, np.ones((32, 32, 3), dtype=np.float32))
        srn_format.write_mask(white / "mask" / png.name, np.zeros((32, 32), dtype=bool))
        srn_format.write_depth(white / "depth" / f"{png.stem}.npz", np.zeros((32, 32), dtype=np.float32))
    torch.manual_seed(0)
    weights = tmp / "bundled.safetensors"
    save_bundled(BundledDepthNet(BundledNetConfig(widths=(8, 8, 8), input_size=32, unshuffle=1)), weights)
    assert cli("depth", "--data", root, "--estimator", "bundled", "--checkpoint", weights, "--splits", "train",
               "--no-progress") == 0
    assert cli("train", "--depth", "none", "--data", root, "--out", tmp / "base", *TINY) == 0
    assert cli("train", "--depth", "bundled", "--depth-checkpoint", weights, "--data", root,
               "--out", tmp / "depth", *TINY) == 0
    return {"tmp": tmp, "root": root, "weights": weights, "base": tmp / "base", "depth": tmp / "depth"}


def test_protocol_views_are_all_but_view_64_with_stride():
    full = protocol_views(251)
    assert full.input_view == 64 and full.others == 250
    assert full.targets == tuple(v for v in range(251) if v != 64)
    strided = protocol_views(251, 5)
    assert strided.targets == tuple([v for v in range(251) if v != 64][::5]) and len(strided.targets) == 50
    assert 64 not in strided.targets and strided.targets[:3] == (0, 5, 10) and strided.targets[13] == 66
    small = protocol_views(10, 3)
    assert small.input_view == 0 and small.targets == (1, 4, 7)
    assert protocol_views(65).input_view == 64 and protocol_views(64).input_view == 0
    for bad in ((251, 0), (1, 1)):
        with pytest.raises(DepthnerfError):
            protocol_views(*bad)


def test_input_views_are_inputs_and_every_other_view_a_target():
    """pixelNeRF's two-view protocol: views 64 and 104 in, the other 249 views out (the definition, written out);
    input views that cannot be are refused in one line."""
    two = protocol_views(251, 25, TWO_VIEW_INPUTS)
    assert two.input_views == (64, 104) and two.input_view == 64 and two.others == 249
    assert two.targets == tuple([v for v in range(251) if v not in (64, 104)][::25])
    assert 104 not in protocol_views(251, 1, (64, 104)).targets
    assert protocol_views(10, 1, (7,)).targets == (0, 1, 2, 3, 4, 5, 6, 8, 9)  # an explicit view on a small object
    assert protocol_views(251).input_views == (INPUT_VIEW,)
    for args, text in [((66, 1, (64, 70)), "input view 70 does not exist: the object has 66 views (0-65)"),
                       ((2, 1, (0, 1)), "needs a target view besides its 2 input views"),
                       ((66, 1, ()), "--input-views needs at least one view index"),
                       ((66, 1, (-1,)), "--input-views must be view indices >= 0"),
                       ((66, 1, (3, 3)), "--input-views names a view twice: 3 3")]:
        with pytest.raises(DepthnerfError, match=re.escape(text)):
            protocol_views(*args)


def test_protocol_text_and_mesh_status_name_what_ran():
    """The protocol line for objects with and without a view 64, with a stride (target counts written out from
    the protocol's definition), and the mesh status for no, some and all predicted meshes empty."""
    from types import SimpleNamespace

    from depthnerf.eval.summary_lines import input_views_record, mesh_status, protocol_text

    mixed = [SimpleNamespace(views=protocol_views(n, 2)) for n in (251, 10)]  # 250 -> 125 and 9 -> 5 targets
    assert protocol_text(mixed, 4, "test", "cars", 2, 64, 64, True) == (
        "SRN protocol: input view 64 (view 0 for objects with <= 64 views), targets = all other 9/250 views with "
        "stride 2 (5/125 views), 2 of 4 objects of cars_test, 64x64, deterministic sampling")
    small = [SimpleNamespace(views=protocol_views(10))]
    assert protocol_text(small, 1, "val", "chairs", 1, 32, 64, False) == (
        "SRN-style protocol: input view 0 (objects have <= 64 views; SRN uses view 64), targets = all other 9 "
        "views, 1 of 1 objects of chairs_val, 32x32 (input view encoded at the training resolution 64x64), "
        "random sampling (render.sampler.eval_random)")
    two = [SimpleNamespace(views=protocol_views(251, 25, TWO_VIEW_INPUTS))]
    assert protocol_text(two, 50, "test", "cars", 25, 128, 64, True) == (
        "two-view SRN protocol (pixelNeRF's): input views 64 and 104, targets = all other 249 views with stride 25 "
        "(10 views), 1 of 50 objects of cars_test, 128x128 (input views encoded at the training resolution 64x64), "
        "deterministic sampling")
    assert protocol_text([SimpleNamespace(views=protocol_views(66, 1, (3, 9)))], 1, "test", "cars", 1, 32, 32,
                         True).startswith("SRN-style protocol: input views 3, 9, targets = all other 64 views")
    # asked for with --input-views: said so, never passed off as the protocol's choice by view count
    asked = [SimpleNamespace(views=protocol_views(251, 50, (0,)))]
    assert protocol_text(asked, 1, "test", "cars", 50, 32, 32, True, chosen=True).startswith(
        "SRN-style protocol: input view 0 (chosen with --input-views; SRN uses view 64), targets = all other 250 ")
    assert protocol_text(small, 1, "val", "chairs", 1, 32, 32, True, chosen=True).startswith(
        "SRN-style protocol: input view 0 (chosen with --input-views; SRN uses view 64), targets = all other 9 ")
    assert protocol_text([SimpleNamespace(views=protocol_views(251, 50, (64,)))], 1, "test", "cars", 50, 32, 32,
                         True, chosen=True).startswith("SRN protocol: input view 64, targets")
    assert input_views_record(mixed) == [[0], [64]] and input_views_record(two) == [64, 104]
    assert mesh_status(0, 2, 3) == "ok: 2 of 3 objects have mesh.ply; "
    assert mesh_status(1, 2, 3) == ("1 of 2 predicted meshes empty (worst-case values in the means); "
                                    "2 of 3 objects have mesh.ply; ")
    assert mesh_status(2, 2, 3).startswith("every predicted mesh is empty (2 of 2)")


def _read_csv(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_eval_baseline_outputs_are_consistent(setup):
    out = setup["tmp"] / "eval_base"
    assert cli("eval", "--run", setup["base"], "--views-stride", "16", "--save-renders", "--out", out,
               "--mesh-resolution", "16", "--mesh-points", "2000", "--no-progress") == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["objects"] == 3 and summary["views"] == 3 * 5
    assert "input view 64" in summary["protocol"] and "with stride 16 (5 views)" in summary["protocol"]
    assert "all other 65 views" in summary["protocol"] and "3 of 3 objects" in summary["protocol"]
    assert summary["method"] == "pixelNeRF (baseline)" and summary["depth_prior"] == "none"
    assert summary["resolution"] == summary["input_resolution"] == 32 and summary["native_resolution"] == [[32, 32]]
    assert summary["checkpoint_sha256"] == ckpt_sha(summary["checkpoint"]) and summary["preset"] == "cpu-cars"
    assert summary["data_card"]["root"] == str(setup["root"].resolve())
    if summary["lpips"] is None:
        assert summary["lpips_status"].startswith("unavailable")
    rows = _read_csv(out / "per_object.csv")
    assert [r["object_id"] for r in rows][-1] == WHITE_ID and len(rows) == 3
    for key in ("psnr", "ssim"):
        values = [float(r[key]) for r in rows]
        assert all(math.isfinite(v) for v in values)
        assert summary[key] == pytest.approx(float(np.mean(values)), abs=1e-12)
    assert rows[-1]["chamfer_l1"] == "" and rows[0]["chamfer_l1"] != "" and summary["geometry_objects"] == 2
    assert summary["chamfer_l1"] == pytest.approx(np.mean([float(r["chamfer_l1"]) for r in rows[:2]]))
    renders = _read_csv(out / "renders.csv")
    expected = [v for v in range(66) if v != 64][::16]
    assert expected == [0, 16, 32, 48, 65]
    assert all(r["input_view"] == "64" and int(r["views"]) == len(expected) for r in rows)  # scored, not 65
    for obj in rows:
        assert [int(r["view"]) for r in renders if r["object_id"] == obj["object_id"]] == expected
    for r in renders:
        pred = srn_format.read_rgb(out / r["render_path"]).astype(np.float64)
        gt = srn_format.read_rgb(out / r["gt_path"]).astype(np.float64)
        rms_png = math.sqrt(np.mean((pred - gt) ** 2))
        rms_float = math.sqrt(10 ** (-float(r["psnr"]) / 10))
        assert abs(rms_png - rms_float) <= 0.5 / 255 + 1e-9  # |rms(a-g) - rms(b-g)| <= rms(a-b) <= half a step
    per_obj = {r["object_id"]: np.mean([float(x["psnr"]) for x in renders if x["object_id"] == r["object_id"]])
               for r in rows}
    assert all(per_obj[r["object_id"]] == pytest.approx(float(r["psnr"]), abs=1e-9) for r in rows)
    assert all((out / "meshes" / f"{r['object_id']}.ply").is_file() for r in rows[:2])
    table = markdown_table([load_summary(out / "summary.json")])
    assert "pixelNeRF (baseline)" in table and "Cars PSNR" in table


def ckpt_sha(path: str) -> str:
    from depthnerf.files import sha256_file

    return sha256_file(Path(path))


def test_constant_field_gives_closed_form_psnr_and_frustum_mesh(setup):
    weights = constant_field(setup["base"] / "checkpoints" / "step_00000001" / "model.safetensors",
                             setup["tmp"] / "constant.safetensors")
    out = setup["tmp"] / "eval_const"
    assert cli("eval", "--checkpoint", weights, "--data", setup["root"], "--out", out, "--resolution", "16",
               "--views-stride", "13", "--save-renders", "--mesh-resolution", "12", "--mesh-points", "500",
               "--scored", "float", "--fp32", "--no-progress") == 0  # the closed form is of the fp32 colour (CUDA: no bf16)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["resolution"] == 16 and summary["input_resolution"] == 32
    assert "16x16 (input view encoded at the training resolution 32x32)" in summary["protocol"]
    records = index_split(setup["root"], "cars", "test").objects
    color = np.array(COLOR)
    views = list(protocol_views(66, 13).targets)
    rows = {r["object_id"]: r for r in _read_csv(out / "per_object.csv")}
    for record in records:
        gts = load_object(record, views, resolution=16, pixel_center=0.0).images.permute(0, 2, 3, 1).double().numpy()
        expected = np.mean([10 * math.log10(1 / np.mean((color - g) ** 2)) for g in gts])
        assert float(rows[record.object_id]["psnr"]) == pytest.approx(expected, abs=1e-3)
    for r in _read_csv(out / "renders.csv"):
        assert r["gt_path"].startswith("gt/")  # resized ground truth is written next to the renders
        assert np.abs(srn_format.read_rgb(out / r["render_path"]) - color).max() <= 0.5 / 255 + 1e-6
    record = records[0]
    src = load_object(record, [64], pixel_center=0.0)
    grid = CameraGrid.from_frustum(src.poses[0], src.intrinsics, 0.8, 1.8)
    step = grid.layout(12)[1]
    mesh = trimesh.load(out / "meshes" / f"{record.object_id}.ply", force="mesh")
    cam = world_to_camera(torch.as_tensor(mesh.vertices, dtype=torch.float32), src.poses[0]).numpy()
    lo, hi = np.array(grid.lo), np.array(grid.hi)
    assert np.all(cam.min(0) <= lo + 1e-4) and np.all(cam.min(0) >= lo - 2 * step)
    assert np.all(cam.max(0) >= hi - 1e-4) and np.all(cam.max(0) <= hi + 2 * step)


def test_depth_aware_eval_needs_the_split_cache_then_runs(setup, capsys):
    out = setup["tmp"] / "eval_depth"
    assert cli("eval", "--run", setup["depth"], "--out", out, "--no-mesh", "--no-progress") == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1
    assert "depthnerf depth" in err and "--splits test" in err and "--resolution 32" in err
    assert cli("depth", "--data", setup["root"], "--estimator", "bundled", "--checkpoint", setup["weights"],
               "--splits", "test", "--resolution", "32", "--no-progress") == 0
    assert cli("eval", "--run", setup["depth"], "--out", out, "--no-mesh", "--views-stride", "30",
               "--no-progress") == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["depth_prior"] == "bundled" and summary["method"] == "depth-aware (bundled)"
    assert summary["objects"] == 3 and summary["views"] == 9  # the all-white object too: finite, no error
    assert all(math.isfinite(o["psnr"]) and math.isfinite(o["ssim"]) for o in summary["per_object"])
    assert summary["chamfer_l1"] is None and summary["mesh_status"] == "skipped (--no-mesh)"
    assert summary["depth_prior_provenance"]["estimator"] == "bundled"
    assert load_summary(out / "summary.json").metrics["psnr"] == summary["psnr"]


def test_eval_small_objects_use_view_0_and_max_objects(setup):
    out = setup["tmp"] / "eval_train"
    assert cli("eval", "--run", setup["base"], "--split", "train", "--out", out, "--max-objects", "1",
               "--method", "label (test)", "--mesh-resolution", "8", "--mesh-points", "100", "--no-progress") == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["protocol"].startswith("SRN-style protocol: input view 0 (objects have <= 64 views; SRN uses "
                                          "view 64), targets = all other 3 views, 1 of 2 objects of cars_train")
    assert summary["objects"] == 1 and summary["views"] == 3 and summary["method"] == "label (test)"
    first = sorted(p.name for p in (setup["root"] / "cars_train").iterdir() if p.is_dir())[0]
    assert [r["object_id"] for r in _read_csv(out / "per_object.csv")] == [first]  # the first by id


def test_eval_on_two_input_views_records_them_and_refuses_to_resume_on_one(setup, capsys):
    """``--input-views 64 10``: every view but those two is a target, the summary, table label and per-object rows
    say so, and the same folder is not resumed by a one-view evaluation."""
    out = setup["tmp"] / "eval_two"
    common = ["--run", setup["base"], "--views-stride", "16", "--out", out, "--no-mesh", "--no-progress"]
    assert cli("eval", *common, "--input-views", "64", "10") == 0
    summary = json.loads((out / "summary.json").read_text())
    targets = [v for v in range(66) if v not in (64, 10)][::16]
    assert summary["input_views"] == [64, 10] and summary["views"] == 3 * len(targets)
    assert summary["protocol"].startswith("SRN-style protocol: input views 64, 10 (chosen with --input-views), "
                                          "targets = all other 64 views "
                                          f"with stride 16 ({len(targets)} views)")
    assert summary["method"] == "pixelNeRF (baseline), 2 input views"
    rows = _read_csv(out / "per_object.csv")
    assert {(r["input_view"], r["input_views"], r["views"]) for r in rows} == {("64", "64 10", str(len(targets)))}
    capsys.readouterr()
    assert cli("eval", *common) == 2
    err = capsys.readouterr().err
    assert "evaluated with other settings (input_views" in err and err.count("\n") == 1


@pytest.mark.parametrize("args, text", [
    (["--checkpoint", "no/such/ckpt", "--out", "x"], "not a checkpoint file"),
    (["--input-views", "64", "70"], "/cars_test/"),  # the object's folder, then what is wrong
    (["--input-views", "64", "70"], ": input view 70 does not exist: the object has 66 views (0-65)"),
    (["--input-views", "64", "64"], "--input-views names a view twice: 64 64"),
    (["--checkpoint", "no/such/ckpt"], "--out OUT_DIR is required"),
    (["--views-stride", "0"], "--views-stride must be >= 1"),
    (["--split", "val"], "split folder does not exist"),
])
def test_eval_bad_input_is_one_line_error(setup, capsys, args, text):
    if "--checkpoint" not in args:
        args = ["--run", str(setup["base"]), "--out", str(setup["tmp"] / "bad"), "--no-mesh", "--no-progress", *args]
    assert cli("eval", *args) == 2
    err = capsys.readouterr().err
    assert text in err and err.count("\n") == 1


def test_checkpoints_lists_shipped_or_says_none(setup, capsys, monkeypatch, tmp_path):
    from depthnerf.pretrained import load as pretrained

    monkeypatch.setattr(pretrained, "SHIPPED_DIR", tmp_path / "empty")
    assert cli("checkpoints") == 0
    assert "no checkpoints are shipped" in capsys.readouterr().out
    shipped = tmp_path / "shipped"
    shipped.mkdir()
    shutil.copy(setup["depth"] / "checkpoints" / "step_00000001" / "model.safetensors",
                shipped / "tiny-cars-depth.safetensors")
    (shipped / "tiny-cars-depth.json").write_text(json.dumps({"metrics": {"psnr": 12.5}, "protocol": "test"}))
    monkeypatch.setattr(pretrained, "SHIPPED_DIR", shipped)
    assert cli("checkpoints") == 0
    line = capsys.readouterr().out
    weights = Path(json.loads((setup["depth"] / "prior.json").read_text())["checkpoint"]).name
    assert (f"tiny-cars-depth: preset cpu-cars, category cars, depth prior bundled ({weights} weights), 1 steps; "
            "psnr 12.5") in line
    assert cli("checkpoints", "--json") == 0
    assert json.loads(capsys.readouterr().out)[0]["metrics"] == {"psnr": 12.5}
    assert load_pretrained("tiny-cars-depth").step == 1  # the name resolves in eval / reconstruct too


def test_retired_checkpoint_name_points_to_its_card(setup, capsys, monkeypatch, tmp_path):
    """A name whose weights no longer ship is one line naming its kept card, in eval and in the listing; a retired
    card does not make its name loadable."""
    from depthnerf.pretrained import load as pretrained

    shipped = tmp_path / "shipped"
    (shipped / "retired").mkdir(parents=True)
    card = shipped / "retired" / "old-cars-sym.md"
    card.write_text("# old-cars-sym\n")
    monkeypatch.setattr(pretrained, "SHIPPED_DIR", shipped)
    assert cli("eval", "--checkpoint", "old-cars-sym", "--out", str(tmp_path / "out")) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "old-cars-sym: a retired checkpoint" in err and str(card) in err
    assert cli("checkpoints") == 0
    assert capsys.readouterr().out.strip().splitlines()[-1].endswith("retired): old-cars-sym")
    assert not (tmp_path / "out").exists()


def test_pixel_center_is_trained_recorded_and_overridable(setup):
    """``--data.pixel_center`` reaches the checkpoint; eval uses the trained value unless ``--pixel-center``
    overrides it (then other rays are rendered and scored), and the summary records both."""
    run = setup["tmp"] / "centred"
    assert cli("train", "--depth", "none", "--data", setup["root"], "--out", run, *TINY,
               "--data.pixel_center", "0.5") == 0
    assert load_pretrained(run).spec.pixel_center == 0.5
    summaries = {}
    for name, extra in (("trained", []), ("override", ["--pixel-center", "0"])):
        out = setup["tmp"] / f"eval_centre_{name}"
        assert cli("eval", "--run", run, "--views-stride", "33", "--max-objects", "1", "--no-mesh", "--out", out,
                   "--no-progress", *extra) == 0
        summaries[name] = json.loads((out / "summary.json").read_text())
    assert summaries["trained"]["pixel_center"] == 0.5 and summaries["override"]["pixel_center"] == 0.0
    assert summaries["trained"]["trained_pixel_center"] == summaries["override"]["trained_pixel_center"] == 0.5
    assert summaries["trained"]["dataset_pixel_center"] == 0.0  # the fixture has no card: integer centres
    assert summaries["trained"]["psnr"] != summaries["override"]["psnr"]
