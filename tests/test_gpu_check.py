"""scripts/gpu_check.sh on the CPU path with tiny settings: the JSON's keys, the kill/resume and same-seed
comparisons, a stage that fails (the benchmark given 1 s) recorded while the later stages still run, pytest's
outcomes counted with the failing id listed, the time budget skipping tests, and the comparison seeing a change.

Skipped where the script cannot run (no bash or no process groups), and inside the GPU check's own pytest stage
(``GPU_CHECK_ACTIVE``), which need not run a second check."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "scripts"))
import gpu_check_parts as parts  # noqa: E402

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(shutil.which("bash") is None or not hasattr(os, "killpg"), reason="needs bash and POSIX"),
    pytest.mark.skipif(bool(os.environ.get("GPU_CHECK_ACTIVE")), reason="inside gpu_check's own pytest stage"),
]

TINY_TESTS = """
import pytest

def test_passes():
    assert True

def test_fails():
    assert 1 == 2, "planted failure"

def test_skips():
    pytest.skip("planted skip")
"""


@pytest.fixture(scope="module")
def check(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("gpu_check")
    (tmp / "test_tiny.py").write_text(TINY_TESTS)
    out = tmp / "out"
    env = {**os.environ, "GPU_CHECK_DEVICE": "cpu", "GPU_CHECK_WORK": str(tmp / "work"),
           "GPU_CHECK_TIMEOUT_BENCH": "0", "GPU_CHECK_STEPS": "4", "GPU_CHECK_CKPT_EVERY": "1",
           "GPU_CHECK_PYTEST_ARGS": f"{tmp / 'test_tiny.py'}", "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(["bash", str(ROOT / "scripts" / "gpu_check.sh"), str(out)], env=env,
                          capture_output=True, text=True, timeout=300)
    return proc, json.loads((out / "gpu_check.json").read_text()), out


def test_the_json_records_every_stage_and_the_device(check):
    proc, result, out = check
    assert proc.returncode == 1, proc.stderr[-2000:]  # the benchmark's stage failed
    assert {"schema", "started", "finished", "host", "device", "cuda", "budget_s", "seconds", "stages", "summary",
            "train_settings"} <= result.keys()
    assert result["finished"] is not None and result["cuda"] is False
    assert {"gpu_name", "torch", "torch_cuda", "python", "cpus", "source_sha256", "packages"} <= result["device"].keys()
    assert list(result["stages"]) == ["env", "bench", "data", "train", "resume_exact", "same_seed", "fast_kernels",
                                      "pytest"]
    for entry in result["stages"].values():
        assert {"status", "seconds", "details"} <= entry.keys() and entry["status"] in ("ok", "failed", "skipped")
    assert result["stages"]["fast_kernels"] == {"status": "skipped", "seconds": 0.0,
                                                "details": {"reason": "needs CUDA"}}
    assert (out / "gpu_check.log").stat().st_size > 0 and "gpu_check: " in proc.stdout


def test_a_failing_stage_is_recorded_and_the_later_ones_still_run(check):
    _, result, _ = check
    bench = result["stages"]["bench"]
    assert bench["status"] == "failed" and bench["details"]["timed_out"] is True and bench["limit_s"] == 1
    assert {k: result["summary"][k] for k in ("env", "data", "train", "resume_exact", "same_seed")} == dict.fromkeys(
        ("env", "data", "train", "resume_exact", "same_seed"), "ok")


def test_kill_resume_and_same_seed_runs_are_compared_bit_for_bit(check):
    _, result, _ = check
    b = result["stages"]["train"]["details"]["b"]
    assert b["rc"] == -9 and b["resume_rc"] == 0 and b["crash_at"] == "state@2" and b["expected_resume_step"] == 1
    for name in ("resume_exact", "same_seed"):
        d = result["stages"][name]["details"]
        assert d["identical"] is True and d["steps_a"] == d["steps_b"] == 4 and d["steps_differing"] == 0
        assert d["model"]["differing"] == 0 and d["optimizer"]["differing"] == 0 and d["model"]["tensors"] > 0
    assert result["stages"]["resume_exact"]["details"]["killed_steps"] == 2  # steps 1-2 before the kill at 2


def test_pytest_outcomes_are_counted_and_the_failure_named(check):
    _, result, out = check
    d = result["stages"]["pytest"]["details"]
    assert result["stages"]["pytest"]["status"] == "failed" and d["reason"] == "1 failed"
    assert d["counts"] == {"passed": 1, "failed": 1, "skipped": 1} and d["collected"] == 3
    assert [f["id"].split("::")[-1] for f in d["failures"]] == ["test_fails"]
    assert "planted failure" in d["failures"][0]["message"] and d["skip_reasons"] == {"planted skip": 1}
    assert d["not_run_budget"] == 0 and d["not_reached"] == 0 and d["rerun_files"] == []
    assert "1 failed" in d["summary_line"]
    assert (out / "pytest_report.jsonl").is_file()


def test_tests_past_the_deadline_are_skipped_and_counted(tmp_path):
    (tmp_path / "test_tiny.py").write_text(TINY_TESTS)
    shutil.copy(ROOT / "scripts" / "gpu_check_pytest.py", tmp_path)
    report = tmp_path / "report.jsonl"
    env = {**os.environ, "GPU_CHECK_DEADLINE": str(time.time() - 1), "GPU_CHECK_REPORT": str(report),
           "PYTHONPATH": f"{tmp_path}:{os.environ.get('PYTHONPATH', '')}"}
    proc = subprocess.run([sys.executable, "-m", "pytest", "-p", "gpu_check_pytest", "-p", "no:cacheprovider",
                           str(tmp_path / "test_tiny.py")], cwd=tmp_path, env=env, capture_output=True, text=True)
    summary = parts.pytest_summary(report, parts.Proc(proc.returncode, proc.stdout, 1.0, False))
    assert summary["counts"] == {"skipped": 3} and summary["not_run_budget"] == 3, proc.stdout[-2000:]
    assert summary["rerun_files"] == ["test_tiny.py"] and summary["collected"] == 3


def test_the_comparison_sees_one_changed_loss_and_one_changed_tensor(check, tmp_path):
    import torch
    from safetensors.torch import load_file, save_file

    from depthnerf.train.checkpoint import latest_checkpoint

    src = check[2].parent / "work" / "runs" / "a"
    copy = tmp_path / "a2"
    shutil.copytree(src, copy)
    lines = (copy / "metrics.jsonl").read_text().splitlines()
    first = json.loads(lines[0])
    first["loss_fine"] = first["loss_fine"] + 1e-7
    (copy / "metrics.jsonl").write_text("\n".join([json.dumps(first), *lines[1:]]) + "\n")
    weights = latest_checkpoint(copy / "checkpoints") / "model.safetensors"
    tensors = load_file(weights)
    name = sorted(k for k, v in tensors.items() if v.is_floating_point())[0]
    tensors[name] = torch.nextafter(tensors[name], torch.full_like(tensors[name], float("inf")))
    save_file(tensors, weights, metadata={"format": "pt"})
    d = parts.compare(src, copy)
    assert d["identical"] is False and d["steps_differing"] == 1 and d["first_differing_step"] == 1
    assert d["model"]["differing"] == 1 and d["model"]["first_differing"] == [name] and d["optimizer"]["differing"] == 0


def test_bench_cases_keep_the_stage_order_and_give_the_last_the_rest():
    cases = [("baseline", ["a"], 0.3), ("compiled_step", ["b"], 0.75), ("view_variants", ["c"], 0.7),
             ("gather", ["d"], 1.0)]
    assert parts.bench_cases(cases, "") == cases
    assert parts.bench_cases(cases, "view_variants,compiled_step") == [("compiled_step", ["b"], 0.75),
                                                                        ("view_variants", ["c"], 1.0)]
    with pytest.raises(ValueError, match=r"unknown cases \['views'\]"):
        parts.bench_cases(cases, "compiled_step views")
