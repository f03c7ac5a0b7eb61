"""``depthnerf eval`` inputs and outputs at their edges: what ``--overwrite`` deletes, flag values that cannot work
(one line naming the flag, before anything loads), symmetry flags on a model without the mirror branch, and
evaluations whose predicted meshes are all empty (eval's line and ``depthnerf compare`` say so).

Tiny random checkpoints (tests/fixtures_checkpoints.py) on a 16 px sphere fixture with meshes: an evaluation takes
seconds.
"""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import pytest
from fixtures_checkpoints import save_tiny, tiny_config
from fixtures_srn import make_srn_fixture

from depthnerf.cli import main
from depthnerf.config_io import apply_overrides
from depthnerf.errors import DepthnerfError
from depthnerf.eval.table import load_summary, markdown_table
from depthnerf.train.config import check_config, preset

PLY_HEADER = ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
              "element face 1\nproperty list uchar int vertex_indices\nend_header\n")
"""An ASCII PLY header for 3 vertices and 1 face; the tests append bodies with problems."""


@pytest.fixture(scope="module")
def case(tmp_path_factory) -> dict[str, Path]:
    """Two test spheres (4 views, 16 px, with mesh.ply) and a plain and a mirror checkpoint."""
    tmp = tmp_path_factory.mktemp("evalinputs")
    root = make_srn_fixture(tmp / "data", "cars", splits={"test": 2}, views=4, size=16, with_mesh=True,
                            with_mask=True)
    cfg = tiny_config("cars", "none")
    return {"tmp": tmp, "root": root, "plain": save_tiny(tmp / "plain.safetensors", cfg),
            "mirror": save_tiny(tmp / "mirror.safetensors", apply_overrides(cfg, ["--model.mirror", "true"]))}


def _eval(case: dict, out: Path, *flags: str, checkpoint: str = "plain") -> int:
    """``depthnerf eval`` of the case's data, with a small mesh unless ``--no-mesh`` is among ``flags``."""
    mesh = [] if "--no-mesh" in flags else ["--mesh-resolution", "8", "--mesh-points", "200"]
    return main(["eval", "--checkpoint", str(case[checkpoint]), "--data", str(case["root"]), "--out", str(out),
                 *mesh, "--no-progress", *[str(f) for f in flags]])


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1, err
    return err


def _files(folder: Path) -> set[str]:
    return {p.relative_to(folder).as_posix() for p in folder.rglob("*")}


def test_overwrite_removes_every_output_of_the_earlier_evaluation_and_nothing_else(case, capsys):
    out = case["tmp"] / "overwrite"
    assert _eval(case, out, "--save-renders", "--resolution", "32") == 0  # 32 px: gt/ copies are written too
    before = _files(out)
    assert {"renders.csv", "gt", "meshes", "renders", "per_object.csv", "summary.json"} <= before
    assert sum(name.startswith("renders/") and name.endswith(".png") for name in before) == 2 * 3
    (out / "notes.txt").write_text("mine")
    (out / "renders" / "keep.txt").write_text("mine too")
    (out / "objects" / ".stale.json.123.tmp").write_text("{")  # a killed writer's leftover
    assert _eval(case, out, "--views-stride", "2", "--overwrite") == 0
    capsys.readouterr()
    objects = {f"objects/{p.name}" for p in (case["root"] / "cars_test").iterdir()}
    assert _files(out) == {"notes.txt", "renders", "renders/keep.txt", "objects", "objects/settings.json",
                           *{f"{o}.json" for o in objects}, "per_object.csv", "summary.json"}
    summary = json.loads((out / "summary.json").read_text())
    assert summary["views_stride"] == 2 and summary["views"] == 2 * 2 and summary["renders_csv"] is None


@pytest.mark.parametrize("inside", ["", "cars_test/scores", "cars_val"])
def test_an_out_inside_the_dataset_is_refused_before_anything_is_written(case, tmp_path, capsys, inside):
    """Written into a split folder, the outputs became an object of it that the next read refused (or, as
    ``cars_val``, a split of their own): the dataset is read, never written into."""
    root = make_srn_fixture(tmp_path / "data", "cars", splits={"test": 1}, views=2, size=16)
    before = _files(root)
    out = root / inside
    assert main(["eval", "--checkpoint", str(case["plain"]), "--data", str(root), "--out", str(out), "--no-mesh",
                 "--no-progress"]) == 2
    assert _one_error_line(capsys) == (f"error: {out}: --out is the dataset {root} or lies in one of its split "
                                       "folders, which eval reads; choose an --out outside them\n")
    assert _files(root) == before


def test_an_out_beside_the_split_folders_is_an_output_folder_like_any(case, tmp_path):
    root = make_srn_fixture(tmp_path / "data", "cars", splits={"test": 1}, views=2, size=16)
    assert main(["eval", "--checkpoint", str(case["plain"]), "--data", str(root), "--out", str(root / "evals" / "a"),
                 "--no-mesh", "--no-progress"]) == 0
    assert (root / "evals" / "a" / "summary.json").is_file()


@pytest.mark.parametrize("name, make", [("per_object.csv", Path.mkdir), ("summary.json", Path.mkdir),
                                        ("objects", Path.touch), ("meshes", Path.touch)])
def test_an_output_name_taken_by_the_other_kind_of_entry_is_one_line(case, tmp_path, capsys, name, make):
    """A folder where eval writes a file (or a file where it writes a folder) was an IsADirectoryError /
    FileExistsError traceback, after every object had been scored for a CSV."""
    out = tmp_path / "out"
    out.mkdir()
    make(out / name)
    assert _eval(case, out, "--views-stride", "2", "--save-renders") == 2
    err = _one_error_line(capsys)
    assert err.startswith(f"error: {out / name}: is a ") and "choose another --out" in err
    assert not (out / "objects" / "settings.json").exists()  # refused before any object was scored


def test_out_of_memory_while_evaluating_is_one_line_naming_the_sizes(case, tmp_path, capsys, monkeypatch):
    """``--resolution 100000`` made the CPU allocator fail in a traceback; it is one line naming the flags that
    size the work, exit 2."""
    import depthnerf.eval.protocol as protocol

    def fail(*args, **kwargs):
        raise MemoryError()

    monkeypatch.setattr(protocol, "evaluate_protocol", fail)
    assert _eval(case, tmp_path / "out", "--resolution", "100000", "--chunk", "64", "--device", "cpu") == 2
    assert _one_error_line(capsys) == ("error: out of memory on cpu (MemoryError) evaluating at --resolution 100000, "
                                       "--chunk 64 rays per pass, --mesh-resolution 8; lower them (the finished "
                                       "objects are kept: the same command continues)\n")


@pytest.mark.parametrize("flags, text", [
    (["--pixel-center", "7"], "--pixel-center must be in [0, 1)"),
    (["--pixel-center", "-100"], "--pixel-center must be in [0, 1)"),
    (["--pixel-center", "1"], "--pixel-center must be in [0, 1)"),
    (["--pixel-center", "nan"], "--pixel-center must be in [0, 1)"),
    (["--fscore-tau", "-1"], "--fscore-tau must be > 0"),
    (["--fscore-tau", "0"], "--fscore-tau must be > 0"),
    (["--fscore-tau", "inf"], "--fscore-tau must be > 0 and finite"),  # every point within: F-score 1, no measure
    (["--fscore-tau", "nan"], "--fscore-tau must be > 0 and finite"),
    (["--mesh-points", "0"], "--mesh-points must be >= 1"),
    (["--symmetry-plane", "0", "0", "0", "0"], "--symmetry-plane: a symmetry plane is 4 finite numbers"),
    (["--guided-align-samples", "-5"], "--guided-align-samples must be >= 1, got -5"),  # was ignored: no --guided
    (["--lpips-trunk", "vgg.pth"], "--lpips-trunk vgg.pth: no such file"),
    (["--samples", "1", "16", "8"], "--samples takes three counts, coarse >= 2, importance >= 0 and Gaussian >= 0, "
                                    "got 1 16 8"),
    (["--samples", "32", "-1", "8"], "got 32 -1 8"),  # was LPIPS "unavailable", exit 0
])
def test_flag_values_that_cannot_work_are_refused_before_anything_loads(tmp_path, capsys, flags, text):
    """A checkpoint path that does not exist: were the flag checked after loading, the error would be about it."""
    assert main(["eval", "--checkpoint", str(tmp_path / "no-such.safetensors"), "--out", str(tmp_path / "out"),
                 *flags]) == 2
    err = _one_error_line(capsys)
    assert text in err and "--data.symmetry_plane" not in err
    assert not (tmp_path / "out").exists()


def test_train_config_refuses_a_pixel_centre_outside_0_1(tmp_path, capsys):
    cfg = preset("cpu-cars")
    for good in ("0", "0.5", "0.999"):
        assert check_config(apply_overrides(cfg, ["--data.pixel_center", good])).data.pixel_center == float(good)
    for bad in ("7", "-0.5", "1", "nan"):
        with pytest.raises(DepthnerfError, match=r"--data\.pixel_center must be in \[0, 1\)"):
            check_config(apply_overrides(cfg, ["--data.pixel_center", bad]))
    assert main(["train", "--data", str(tmp_path), "--out", str(tmp_path / "run"), "--data.pixel_center", "7"]) == 2
    assert "--data.pixel_center must be in [0, 1)" in _one_error_line(capsys)
    assert not (tmp_path / "run").exists()


def test_symmetry_flags_on_a_model_without_the_mirror_branch_are_a_note(case, capsys):
    plain = _eval(case, case["tmp"] / "sym_plain", "--no-mesh", "--symmetry-plane", "0", "1", "0", "0")
    assert plain == 0
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("note:")]
    assert len(err) == 1 and "--symmetry-plane has no effect" in err[0]
    assert "no mirror-symmetric conditioning" in err[0] and str(case["plain"]) in err[0]
    assert _eval(case, case["tmp"] / "sym_plain2", "--no-mesh", "--no-symmetry") == 0
    assert "note: --no-symmetry has no effect" in capsys.readouterr().err
    # a mirror model takes the plane, says which flag gave it, and gets no note
    assert _eval(case, case["tmp"] / "sym_mirror", "--no-mesh", "--symmetry-plane", "0", "2", "0", "0",
                 checkpoint="mirror") == 0
    assert "note:" not in capsys.readouterr().err
    summary = json.loads((case["tmp"] / "sym_mirror" / "summary.json").read_text())
    assert summary["symmetry_plane"] == [0.0, 1.0, 0.0, 0.0] and summary["symmetry_plane_source"] == "--symmetry-plane"


def test_all_empty_meshes_are_said_in_eval_line_summary_and_compare(case, capsys):
    """A density level no point reaches leaves every predicted mesh empty: worst-case Chamfer-L1 1 and F-score 0,
    which the printed line, mesh_status and the compare table must not pass off as measured."""
    out = case["tmp"] / "empty"
    assert _eval(case, out, "--mesh-threshold", "1e12") == 0
    line = capsys.readouterr().out.splitlines()[0]
    assert "Chamfer-L1 1.0000, F-score@0.01 0.000 (2 of 2 meshes empty)" in line
    summary = json.loads((out / "summary.json").read_text())
    assert summary["empty_predictions"] == 2 and summary["geometry_objects"] == 2
    assert summary["chamfer_l1"] == 1.0 and summary["fscore"] == 0.0
    assert summary["mesh_status"].startswith("every predicted mesh is empty (2 of 2)")
    assert main(["compare", str(out)]) == 0
    table = capsys.readouterr().out
    row = next(ln for ln in table.splitlines() if ln.startswith("| pixelNeRF"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[3:6] == ["1.0000 (2/2 meshes empty)", "0.000 (2/2 meshes empty)", "0.000 (2/2 meshes empty)"]
    assert "2/2 meshes empty: their Chamfer-L1 / F-score are worst-case values" in table


def test_compare_marks_partly_empty_meshes_and_leaves_full_ones_plain(tmp_path):
    base = {"psnr": 20.0, "ssim": 0.8, "objects": 3, "views": 9, "checkpoint_sha256": "ab" * 32, "preset": "p",
            "category": "cars", "depth_prior": "none", "protocol": "t", "chamfer_l1": 0.05, "fscore": 0.5}
    paths = []
    for name, extra in (("a", {"empty_predictions": 1, "geometry_objects": 3}),
                        ("b", {"empty_predictions": 0, "geometry_objects": 3}), ("c", {})):
        paths.append(tmp_path / f"{name}.json")
        paths[-1].write_text(json.dumps({**base, "method": name, **extra}))
    rows = {ln.split("|")[1].strip(): [c.strip() for c in ln.strip("|").split("|")[1:]]
            for ln in markdown_table([load_summary(p) for p in paths]).splitlines() if ln.startswith("| ")}
    assert rows["a"][2:] == ["0.0500 (1/3 meshes empty)", "0.500 (1/3 meshes empty)"]
    assert rows["b"][2:] == rows["c"][2:] == ["0.0500", "0.500"]
    paths[0].write_text(json.dumps({**base, "method": "a", "empty_predictions": -1}))
    with pytest.raises(DepthnerfError, match="'empty_predictions' must be a non-negative integer"):
        load_summary(paths[0])


def test_max_objects_checks_the_files_of_the_objects_it_scores(case, tmp_path, capsys):
    """``--max-objects N`` reads and checks the files of the N objects it evaluates, not the whole split's: a
    broken pose in another object does not stop it, while the whole split's evaluation names that file."""
    root = tmp_path / "data"
    shutil.copytree(case["root"], root)
    second = sorted(p for p in (root / "cars_test").iterdir() if p.is_dir())[1]
    broken = sorted((second / "pose").iterdir())[0]
    broken.write_text("not a pose\n")
    flags = ["--checkpoint", str(case["plain"]), "--data", str(root), "--no-mesh", "--no-progress"]
    assert main(["eval", *flags, "--out", str(tmp_path / "one"), "--max-objects", "1"]) == 0
    summary = json.loads((tmp_path / "one" / "summary.json").read_text())
    assert summary["objects"] == 1 and ", 1 of 2 objects of cars_test," in summary["protocol"]
    capsys.readouterr()
    assert main(["eval", *flags, "--out", str(tmp_path / "all")]) == 2
    assert str(broken) in _one_error_line(capsys)


def test_gather_inside_reaches_the_fields_and_scores_the_same(case, tmp_path, monkeypatch):
    """``eval --gather inside``: the session's fields gather in the MLP forward (``torch.compile`` replaced by the
    eager forward here, so no compilation) and the scores are those of the gather before the MLP up to float rounding."""
    import depthnerf.render.precision as precision

    seen = []
    monkeypatch.setattr(precision.torch, "compile", lambda fn, **kw: seen.append(kw) or fn)
    psnr = {}
    for gather in ("before", "inside"):
        assert _eval(case, tmp_path / gather, "--no-mesh", "--gather", gather) == 0
        psnr[gather] = json.loads((tmp_path / gather / "summary.json").read_text())["psnr"]
    assert len(seen) == 2  # the inside run's coarse and fine forwards (--gather inside implies --compile)
    assert psnr["inside"] == pytest.approx(psnr["before"], abs=1e-4)


@pytest.mark.parametrize("body, problem", [
    ("0 0 0\n1 0 0\n0 1 0\n3 0 1 99\n", "face 0 names vertex 99, but the mesh has 3 vertices (0-2)"),
    ("0 0 0\nnan 0 0\n0 1 0\n3 0 1 2\n", "mesh has non-finite vertices"),
])
def test_a_bad_ground_truth_mesh_is_one_warning_and_that_object_goes_unscored(case, tmp_path, capsys, body: str,
                                                                               problem: str):
    """mesh.ply is optional: a face naming a missing vertex or a NaN vertex turns it off for its object (one
    warning naming the file) as for an object without one; the other object is still scored."""
    root = tmp_path / "data"
    shutil.copytree(case["root"], root)
    bad = sorted((root / "cars_test").iterdir())[0] / "mesh.ply"
    bad.write_text(PLY_HEADER + body)
    out = tmp_path / "eval"
    assert main(["eval", "--checkpoint", str(case["plain"]), "--data", str(root), "--out", str(out),
                 "--mesh-resolution", "8", "--mesh-points", "200", "--no-progress"]) == 0
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith(("warning", "error"))]
    assert err == [f"warning: {bad}: {problem}; mesh.ply not used for this object"]
    summary = json.loads((out / "summary.json").read_text())
    assert "1 of 2 objects have mesh.ply" in summary["mesh_status"], summary["mesh_status"]
    rows = {row["object_id"]: row for row in csv.DictReader((out / "per_object.csv").open())}
    assert rows[bad.parent.name]["chamfer_l1"] == "" and rows[bad.parent.name]["psnr"] != ""
    assert all(row["chamfer_l1"] != "" for name, row in rows.items() if name != bad.parent.name)


def test_without_mesh_scoring_only_the_mesh_header_is_checked(case, tmp_path, capsys):
    """``--no-mesh`` scores no geometry, so indexing reads only each mesh.ply's header (as training does): a bad
    body is not read, and no warning about a part that is not used anyway."""
    root = tmp_path / "data"
    shutil.copytree(case["root"], root)
    bad = sorted((root / "cars_test").iterdir())[0] / "mesh.ply"
    bad.write_text(PLY_HEADER + "0 0 0\n1 0 0\n0 1 0\n3 0 1 99\n")  # a face naming a missing vertex
    out = tmp_path / "eval"
    assert main(["eval", "--checkpoint", str(case["plain"]), "--data", str(root), "--out", str(out), "--no-mesh",
                 "--no-progress"]) == 0
    assert [line for line in capsys.readouterr().err.splitlines() if line.startswith(("warning", "error"))] == []
    assert json.loads((out / "summary.json").read_text())["mesh_status"] == "skipped (--no-mesh)"


def test_samples_replace_the_sampler_counts_and_are_part_of_the_settings(case, tmp_path, capsys):
    """``--samples`` equal to the checkpoint's trained counts (8 4 2) scores exactly what the checkpoint's sampler
    does; other counts render otherwise, are recorded in summary.json and the method label, and an evaluation
    folder of the other counts is not resumed into."""
    summaries = {}
    for name, flags in (("own", []), ("same", ["--samples", 8, 4, 2]), ("more", ["--samples", 16, 8, 4])):
        assert _eval(case, tmp_path / name, "--no-mesh", *flags) == 0
        summaries[name] = json.loads((tmp_path / name / "summary.json").read_text())
    assert summaries["same"]["psnr"] == summaries["own"]["psnr"]
    assert summaries["more"]["psnr"] != summaries["own"]["psnr"]
    assert [s["sampler_counts"] for s in summaries.values()] == [[8, 4, 2], [8, 4, 2], [16, 8, 4]]
    assert summaries["more"]["method"].endswith(" + 16+8+4 samples/ray")
    capsys.readouterr()
    assert _eval(case, tmp_path / "own", "--no-mesh", "--samples", 16, 8, 4) == 2
    assert "settings" in _one_error_line(capsys)
