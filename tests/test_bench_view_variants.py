"""``benchmarks/bench_view_variants.py``: the accuracy part against ``depthnerf eval``'s own figures for the same
checkpoint and objects (its fp32 row is the CPU policy's eval, exactly), and the speed part's code path on the CPU
(what the GPU lease runs, shrunk: two eager variants at 8 px)."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from fixtures_srn import make_srn_fixture
from test_bench_guided import tiny_checkpoint

from depthnerf.eval.protocol import ProtocolConfig, evaluate_protocol
from depthnerf.infer.session import InferenceSession, SessionOptions

BENCH = Path(__file__).resolve().parent.parent / "benchmarks" / "bench_view_variants.py"


def run_bench(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(BENCH), *args], capture_output=True, text=True, timeout=600,
                          env={"OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin",
                               **{k: os.environ[k] for k in ("PYTHONPATH",) if k in os.environ}})


def test_accuracy_rows_are_the_protocols_psnr_under_each_precision(tmp_path):
    data = make_srn_fixture(tmp_path / "data", splits={"test": 2}, views=66, size=16, with_depth=True)
    ckpt = tiny_checkpoint(tmp_path / "tiny.safetensors")
    out = tmp_path / "acc.json"
    r = run_bench("--checkpoint", str(ckpt), "--data", str(data), "--objects", "2", "--views-stride", "20",
                  "--device", "cpu", "--json", str(out))
    assert r.returncode == 0, r.stderr[-2000:]
    figures = json.loads(out.read_text())
    session = InferenceSession(ckpt, SessionOptions(device="cpu", inputs="dataset", data_root=data))
    ref = evaluate_protocol(session, tmp_path / "eval", ProtocolConfig(views_stride=20, max_objects=2, mesh=False,
                                                                       progress=False))
    assert figures["psnr"]["fp32"] == ref.summary["psnr"]
    for name in ("bf16", "bf16+bf16res"):
        assert figures["psnr"][name] != figures["psnr"]["fp32"]  # bf16 autocast did run
        assert figures[f"{name}_minus_fp32"]["largest_abs"] < 0.5
        assert figures[f"{name}_minus_fp32"]["mean"] == pytest.approx(figures["psnr"][name] - figures["psnr"]["fp32"])
    assert "bf16+bf16res - fp32, per object" in r.stdout


def test_the_speed_variants_run_on_a_named_cpu(tmp_path):
    out = tmp_path / "speed.json"
    r = run_bench("--device", "cpu", "--resolution", "8", "--views", "1", "--repeat", "1",
                  "--variants", "eager", "eager+bf16res", "--json", str(out))
    assert r.returncode == 0, r.stderr[-2000:]
    rows = json.loads(out.read_text())["variants"]
    assert list(rows) == ["eager", "eager+bf16res"] and rows["eager+bf16res"]["flags"] == {"bf16_residual": True}
    for row in rows.values():
        assert row["ms_per_view"] > 0 and 0 < row["max_abs_diff_vs_fp32"] < 0.05
    assert rows["eager"]["max_abs_diff_vs_fp32"] != rows["eager+bf16res"]["max_abs_diff_vs_fp32"]


def test_a_bf16_residual_evaluation_is_not_resumed_as_another(tmp_path):
    """The residual dtype is part of what an evaluation's results depend on: it is recorded, and resuming a
    bf16-stream evaluation with the default policy is refused (its objects would mix two precisions)."""
    import torch

    from depthnerf.errors import DepthnerfError
    from depthnerf.render.precision import inference_policy

    data = make_srn_fixture(tmp_path / "data", splits={"test": 1}, views=66, size=16, with_depth=True)
    ckpt = tiny_checkpoint(tmp_path / "tiny.safetensors")
    policy = dataclasses.replace(inference_policy("cpu"), autocast=torch.bfloat16, residual=torch.bfloat16)
    cfg = ProtocolConfig(views_stride=30, max_objects=1, mesh=False, progress=False)
    out = tmp_path / "eval"
    evaluate_protocol(InferenceSession(ckpt, SessionOptions(device="cpu", inputs="dataset", data_root=data,
                                                            policy=policy)), out, cfg)
    assert json.loads((out / "objects" / "settings.json").read_text())["residual"] == "torch.bfloat16"
    default = InferenceSession(ckpt, SessionOptions(device="cpu", inputs="dataset", data_root=data))
    with pytest.raises(DepthnerfError, match="residual"):
        evaluate_protocol(default, out, cfg)


def test_the_inside_variants_compile_with_inductor_on_a_named_cpu(tmp_path):
    """The gather in the compiled graph from bf16 maps, with the ReLU epilogue: inductor's code (C++ on the CPU) for
    the paper's MLPs renders what the fp32 reference renders, to bf16 rounding (1 view of 8 px)."""
    out = tmp_path / "inside.json"
    r = run_bench("--device", "cpu", "--resolution", "8", "--views", "1", "--repeat", "1",
                  "--variants", "compiled+inside-bf16+relu-ep", "--json", str(out))
    assert r.returncode == 0, r.stderr[-2000:]
    row = json.loads(out.read_text())["variants"]["compiled+inside-bf16+relu-ep"]
    assert row["flags"] == {"compile": True, "gather": "inside-bf16"} and row["runtime_fields"] == {"relu_epilogue": True}
    assert row["ms_per_view"] > 0 and 0 < row["max_abs_diff_vs_fp32"] < 0.05
