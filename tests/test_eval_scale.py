"""``depthnerf eval`` at scale: torchrun sharding (gloo on CPU), per-object result files and exact resume.

Ground truth is the one-process, uninterrupted evaluation of the same checkpoint on the same data: a 2-process
run and a killed-then-restarted run must write the same ``per_object.csv`` (timing column aside), the same
``renders.csv`` and the same ``summary.json`` (timing and ``world_size`` aside), and a restart must not compute
the objects that were finished. Every process runs with ``OMP_NUM_THREADS=1`` so all of them do the same
arithmetic.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from fixtures_checkpoints import save_tiny, tiny_config
from fixtures_srn import make_srn_fixture

from depthnerf.cli import main
from depthnerf.data.srn import index_split
from depthnerf.errors import DepthnerfError
from depthnerf.eval.shards import OBJECTS_DIR, SETTINGS_FILE

ROOT = Path(__file__).resolve().parent.parent
OBJECTS = 5
"""Test objects of the fixture (an odd number, so the two ranks get different shares)."""


def depthnerf(*args: str, env: dict | None = None, nproc: int = 1) -> subprocess.CompletedProcess:
    """``python -m depthnerf ARGS`` (``nproc`` > 1: under ``torchrun --standalone``) from this checkout."""
    launcher = ([sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={nproc}"]
                if nproc > 1 else [sys.executable])
    full_env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT), **(env or {})}
    return subprocess.run([*launcher, "-m", "depthnerf", *map(str, args)], capture_output=True, text=True,
                          env=full_env, cwd=ROOT)


@pytest.fixture(scope="module")
def case(tmp_path_factory) -> dict:
    """Data (5 test objects x 66 views of 16 px, with depth, masks and meshes) and a tiny random checkpoint."""
    tmp = tmp_path_factory.mktemp("evalscale")
    root = make_srn_fixture(tmp / "data", "cars", {"test": OBJECTS}, views=66, size=16, with_depth=True,
                            with_mask=True, with_mesh=True)
    weights = save_tiny(tmp / "tiny.safetensors", tiny_config("cars", "none", resolution=16))
    args = ["eval", "--checkpoint", weights, "--data", root, "--views-stride", "30", "--mesh-resolution", "8",
            "--mesh-points", "300", "--save-renders", "--no-progress", "--device", "cpu"]  # gloo ranks on the CPU
    reference = tmp / "reference"
    done = depthnerf(*args, "--out", reference)
    assert done.returncode == 0, done.stderr[-3000:]
    return {"tmp": tmp, "root": root, "weights": weights, "args": args, "reference": reference}


def _rows(path: Path, drop: tuple[str, ...] = ()) -> list[dict]:
    with open(path, newline="") as f:
        return [{k: v for k, v in row.items() if k not in drop} for row in csv.DictReader(f)]


def outputs(out: Path) -> dict:
    """What must not depend on how the evaluation was run."""
    summary = json.loads((out / "summary.json").read_text())
    return {"per_object": _rows(out / "per_object.csv", drop=("seconds",)), "renders": _rows(out / "renders.csv"),
            "summary": {k: v for k, v in summary.items() if k not in ("timing", "world_size")}}


def test_reference_run_writes_one_result_file_per_object(case):
    objects = case["reference"] / OBJECTS_DIR
    assert sorted(p.name for p in objects.iterdir()) == sorted(
        [SETTINGS_FILE] + [f"{r['object_id']}.json" for r in _rows(case["reference"] / "per_object.csv")])
    summary = json.loads((case["reference"] / "summary.json").read_text())
    assert summary["world_size"] == 1 and summary["objects"] == OBJECTS and summary["geometry_objects"] == OBJECTS
    assert summary["timing"]["objects_computed"] == OBJECTS and summary["timing"]["objects_resumed"] == 0


@pytest.mark.slow
def test_two_gloo_processes_equal_one_process(case):
    out = case["tmp"] / "two"
    done = depthnerf(*case["args"], "--out", out, nproc=2)
    assert done.returncode == 0, done.stderr[-3000:]
    assert outputs(out) == outputs(case["reference"])
    summary = json.loads((out / "summary.json").read_text())
    assert summary["world_size"] == 2 and summary["timing"]["objects_computed"] == OBJECTS
    assert done.stdout.count("wrote ") == 1  # rank 0 alone reports
    refused = depthnerf(*case["args"], "--out", out, "--views-stride", "20", nproc=2)
    assert refused.returncode != 0 and refused.stderr.count("error: ") == 1  # rank 0 says why, rank 1 is silent
    assert "views_stride 30 there, 20 now" in refused.stderr


@pytest.mark.slow
def test_killed_evaluation_resumes_without_recomputing(case):
    """SIGKILL right after the 2nd object's result file (the test hook), a stray half-written temporary file
    beside them, then the same command: the 3 missing objects are computed, the 2 finished ones are not."""
    out = case["tmp"] / "killed"
    killed = depthnerf(*case["args"], "--out", out, env={"DEPTHNERF_CRASH_AT": "eval-object@2"})
    assert killed.returncode == -signal.SIGKILL, killed.stderr[-2000:]
    assert not (out / "summary.json").exists()
    finished = sorted(p for p in (out / OBJECTS_DIR).glob("*.json") if p.name != SETTINGS_FILE)
    assert len(finished) == 2
    stamps = {p: p.stat().st_mtime_ns for p in finished}
    (out / OBJECTS_DIR / f".{finished[0].name}.99999.tmp").write_text('{"format": "depthnerf-eval-obj')
    resumed = depthnerf(*case["args"], "--out", out)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert f"2 of {OBJECTS} objects already evaluated, {OBJECTS - 2} to go" in resumed.stderr
    assert {p: p.stat().st_mtime_ns for p in finished} == stamps  # finished objects were not written again
    timing = json.loads((out / "summary.json").read_text())["timing"]
    assert (timing["objects_computed"], timing["objects_resumed"]) == (OBJECTS - 2, 2)
    assert timing["per_object_s"] == pytest.approx(timing["total_s"] / (OBJECTS - 2))  # the resumed cost nothing
    assert outputs(out) == outputs(case["reference"])


@pytest.mark.slow
def test_killed_torchrun_evaluation_resumes_in_one_process(case):
    """Both ranks killed after their first object (torchrun stops the job), then one process finishes it."""
    out = case["tmp"] / "killed2"
    killed = depthnerf(*case["args"], "--out", out, nproc=2, env={"DEPTHNERF_CRASH_AT": "eval-object@1"})
    assert killed.returncode != 0
    done = [p for p in (out / OBJECTS_DIR).glob("*.json") if p.name != SETTINGS_FILE]
    assert 1 <= len(done) <= 2
    resumed = depthnerf(*case["args"], "--out", out)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert json.loads((out / "summary.json").read_text())["timing"]["objects_resumed"] == len(done)
    assert outputs(out) == outputs(case["reference"])


def test_other_settings_are_refused_unless_overwrite(case, capsys, tmp_path):
    out = tmp_path / "out"
    base = [*case["args"], "--out", out]
    assert main([str(a) for a in base]) == 0
    capsys.readouterr()
    assert main([str(a) for a in base] + ["--views-stride", "20"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"error: {out}: holds {OBJECTS} objects evaluated with other")
    assert "views_stride 30 there, 20 now" in err and "--overwrite" in err
    assert main([str(a) for a in base] + ["--ssim", "gaussian11"]) == 2
    assert "choices.ssim \"uniform7\" there, \"gaussian11\" now" in capsys.readouterr().err
    # settings that do not change a per-object result are free: the label, the object count, the progress bar
    assert main([str(a) for a in base] + ["--method", "renamed", "--max-objects", "3"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["method"] == "renamed" and summary["objects"] == 3
    assert summary["timing"]["objects_computed"] == 0
    assert main([str(a) for a in base] + ["--views-stride", "20", "--overwrite"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["views_stride"] == 20 and summary["timing"]["objects_computed"] == OBJECTS
    assert summary["timing"]["objects_resumed"] == 0


def test_unreadable_or_foreign_result_files_are_computed_again(case, tmp_path):
    """A result file that does not parse, or that another evaluation wrote, never enters the merge."""
    out = tmp_path / "out"
    mesh_flags = {"--mesh-resolution", "--mesh-points"}  # each with a value: refused with --no-mesh
    args = [a for i, a in enumerate(case["args"]) if a not in mesh_flags and case["args"][i - 1] not in mesh_flags]
    base = [str(a) for a in [*args, "--out", out, "--no-mesh"]]
    assert main(base) == 0
    files = sorted(p for p in (out / OBJECTS_DIR).glob("*.json") if p.name != SETTINGS_FILE)
    reference = (out / "per_object.csv").read_text()
    files[0].write_text(files[0].read_text()[:40])  # truncated
    foreign = json.loads(files[1].read_text())
    foreign["settings_sha"] = "0" * 16
    foreign["metrics"]["psnr"] = 99.0
    files[1].write_text(json.dumps(foreign))
    assert main(base) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert (summary["timing"]["objects_computed"], summary["timing"]["objects_resumed"]) == (2, OBJECTS - 2)
    assert [r for r in _rows(out / "per_object.csv", ("seconds",))] == [
        {k: v for k, v in r.items() if k != "seconds"} for r in csv.DictReader(reference.splitlines())]


def test_summary_means_are_recomputed_from_the_object_files(case):
    """The result files alone give the summary: each object's PSNR/SSIM is the mean of its views' (the input view
    not among them), and the summary's the mean over the objects' files, each object once."""
    import numpy as np

    out = case["reference"]
    summary = json.loads((out / "summary.json").read_text())
    files = sorted(p for p in (out / OBJECTS_DIR).glob("*.json") if p.name != SETTINGS_FILE)
    payloads = [json.loads(p.read_text()) for p in files]
    assert sorted(p["object_id"] for p in payloads) == sorted(o["object_id"] for o in summary["per_object"])
    assert len({p["object_id"] for p in payloads}) == summary["objects"] == OBJECTS
    for p in payloads:
        views = p["metrics"]["views"]
        assert len(views) == 3 and [int(r["view"]) for r in p["renders"]] == [0, 30, 60]  # 65 others, stride 30
        for key in ("psnr", "ssim"):
            assert p["metrics"][key] == pytest.approx(np.mean([v[key] for v in views]), abs=1e-12)
    for key in ("psnr", "ssim"):
        assert summary[key] == pytest.approx(np.mean([p["metrics"][key] for p in payloads]), abs=1e-12)
    assert summary["views"] == sum(len(p["metrics"]["views"]) for p in payloads)
    meshed = [p["geometry"] for p in payloads if p["geometry"] is not None]
    assert summary["chamfer_l1"] == pytest.approx(np.mean([g["chamfer_l1"] for g in meshed]), abs=1e-12)


def _synth(root: Path, seed: int) -> None:
    """Two synthetic test cars (66 views of 16 px) of ``seed`` in ``root``, as ``depthnerf synth`` makes them."""
    assert main(["synth", "--category", "cars", "--out", str(root), "--train-objects", "0", "--val-objects", "0",
                 "--test-objects", "2", "--resolution", "16", "--views-test", "66", "--seed", str(seed),
                 "--quiet"]) == 0


def _timing(out: Path) -> tuple[int, int]:
    timing = json.loads((out / "summary.json").read_text())["timing"]
    return timing["objects_computed"], timing["objects_resumed"]


def test_data_generated_again_in_place_is_refused_on_resume(case, tmp_path, capsys):
    """``depthnerf synth`` with another seed into the same folder: the same object ids and (the test split's
    camera spiral) the same poses, other cars. Resuming there mixed the earlier cars' results with the new ones';
    it is one line now. New file times alone (a copy without ``-p``) change nothing; an evaluation whose result
    files predate the fingerprint resumes as before; ``--overwrite`` starts over."""
    root, out = tmp_path / "data", tmp_path / "eval"
    _synth(root, seed=0)
    base = ["eval", "--checkpoint", str(case["weights"]), "--data", str(root), "--views-stride", "30", "--no-mesh",
            "--no-progress", "--device", "cpu", "--out", str(out)]
    assert main(base) == 0 and _timing(out) == (2, 0)
    for path in root.rglob("*"):
        os.utime(path, (1_000_000_000, 1_000_000_000))
    assert main(base) == 0 and _timing(out) == (0, 2)
    shutil.rmtree(root)
    _synth(root, seed=1)
    capsys.readouterr()
    assert main(base) == 2
    first = root / "cars_test" / "synth_cars_test_000000"
    assert capsys.readouterr().err == (
        f"error: {out}: the data changed since the evaluation there started ({first} and 1 more of the 2 finished "
        "objects: other cameras, image sizes or dataset card than its result was computed from); pass --overwrite "
        "to start over or choose another --out\n")
    files = sorted(p for p in (out / OBJECTS_DIR).glob("*.json") if p.name != SETTINGS_FILE)
    for path in files:  # as an evaluation made before the fingerprint wrote them
        payload = json.loads(path.read_text())
        del payload["data_fingerprint"]
        path.write_text(json.dumps(payload))
    assert main(base) == 0 and _timing(out) == (0, 2)
    assert main([*base, "--overwrite"]) == 0 and _timing(out) == (2, 0)
    assert main(base) == 0 and _timing(out) == (0, 2)


def test_the_data_fingerprint_reads_content_not_times(tmp_path):
    """What changes an object's fingerprint: its cameras, its files' sizes, the dataset card's description; what
    does not: file times, and the card's tallies over the splits (another split generated into the folder)."""
    from depthnerf.data.fingerprint import DataFingerprint

    root = make_srn_fixture(tmp_path / "data", "cars", {"test": 1}, views=3, size=16, with_depth=True,
                            with_mask=True, with_mesh=True)
    record = index_split(root, "cars", "test").objects[0]

    def now() -> str:
        return DataFingerprint(root, "cars")(record)

    bare = now()
    assert bare.startswith("files-1:")
    for path in root.rglob("*"):
        os.utime(path, (1_000_000_000, 1_000_000_000))
    assert now() == bare
    card = root / "cars_card.json"
    card.write_text(json.dumps({"seed": 0, "counts": {"train": 10, "test": 1}, "styles": {}, "z_range": {}}))
    carded = now()
    assert carded != bare
    card.write_text(json.dumps({"seed": 0, "counts": {"train": 20, "test": 1}, "styles": {"train": {"suv": 3}},
                                "z_range": {"near": 0.8}}))
    assert now() == carded
    card.write_text(json.dumps({"seed": 1, "counts": {"train": 20, "test": 1}}))
    assert now() != carded
    card.unlink()
    for changed in (record.pose_path(1), record.rgb_path(2), record.depth_path(0), record.mask_path(0),
                    record.mesh_path):
        kept = changed.read_bytes()
        changed.write_bytes(kept + b"\n")
        assert now() != bare, changed
        changed.write_bytes(kept)
    assert now() == bare
    record.pose_path(0).unlink()
    with pytest.raises(DepthnerfError, match=f"^{record.pose_path(0)}: cannot read it"):
        now()
