"""``benchmarks/bench_guided_sampling.py --checkpoint``: a tiny random depth-aware checkpoint (oracle prior) on a
tiny SRN fixture whose test objects have 66 views (view 64 is the input). Ground truth: the reference row is
what ``depthnerf eval`` (the protocol driver) measures for the same checkpoint, objects and views, and its
network evaluations per ray are the sampler's closed form."""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import sys
from pathlib import Path

import pytest
import torch
from fixtures_srn import make_srn_fixture

from depthnerf.config_io import to_dict
from depthnerf.errors import DepthnerfError
from depthnerf.eval.protocol import ProtocolChoices, ProtocolConfig, evaluate_protocol
from depthnerf.infer.session import InferenceSession, SessionOptions
from depthnerf.model.config import EncoderConfig, FieldConfig, PixelNeRFConfig
from depthnerf.model.pixelnerf import PixelNeRF
from depthnerf.render.config import DEFAULT_BUDGET, GuidedConfig, RenderConfig, SamplerConfig
from depthnerf.train import checkpoint as ckpt
from depthnerf.train.config import DataConfig, preset, with_prior

BENCH_DIR = Path(__file__).resolve().parent.parent / "benchmarks"
FLOAT = ProtocolChoices(scored="float")
"""The benchmark scores float renders: the eval it is checked against does too."""


@pytest.fixture(scope="module")
def bench():
    """The benchmark script as a module (its sibling ``guided_checkpoint`` importable)."""
    sys.path.insert(0, str(BENCH_DIR))
    try:
        spec = importlib.util.spec_from_file_location("bench_guided_sampling", BENCH_DIR / "bench_guided_sampling.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = module  # dataclasses look their module up while the script is executed
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.modules.pop("bench_guided_sampling", None)
        sys.path.remove(str(BENCH_DIR))


def tiny_checkpoint(path: Path) -> Path:
    """A random depth-aware model (oracle prior) at 16x16 with a 6 + (6 + 4 + 2) sampler, saved as training does."""
    cfg = with_prior(preset("cpu-cars"), "oracle")
    small = FieldConfig(d_hidden=16, n_blocks=2, combine_layer=1, density_bias_init=5.0)
    model_cfg = PixelNeRFConfig(encoder=EncoderConfig(backbone="resnet18", num_layers=2,
                                                      depth_hidden=8, depth_channels=8), coarse=small, fine=small)
    cfg = dataclasses.replace(cfg, data=DataConfig(category="cars", resolution=16), model=model_cfg,
                              render=RenderConfig(sampler=SamplerConfig(n_coarse=6, n_importance=4, n_gaussian=2)))
    torch.manual_seed(0)
    model = PixelNeRF(model_cfg, depth_aware=True)
    ckpt.save_weights(path, model, to_dict(model_cfg), step=7, extra={"train_config": json.dumps(to_dict(cfg))})
    return path


def run_checkpoint_bench(bench, tmp_path: Path, budgets: str) -> tuple[Path, Path, dict]:
    """A 2-object fixture with depth and masks, a tiny depth-aware checkpoint, and the benchmark's JSON on them
    (every 20th view, one repeat): ``(data root, weights, result)``."""
    root = make_srn_fixture(tmp_path / "data", "cars", {"test": 2}, views=66, size=16, with_depth=True,
                            with_mask=True)
    weights = tiny_checkpoint(tmp_path / "tiny.safetensors")
    out = tmp_path / "bench.json"
    assert bench.main(["--checkpoint", str(weights), "--data", str(root), "--objects", "2", "--views-stride", "20",
                       "--budgets", budgets, "--repeats", "1", "--json", str(out)]) == 0
    return root, weights, json.loads(out.read_text())


def test_checkpoint_mode_matches_eval_protocol(bench, tmp_path):
    root, weights, result = run_checkpoint_bench(bench, tmp_path, "6,12")
    rows = {r["name"]: r for r in result["rows"]}
    assert list(rows) == ["reference", "guided-6", "guided-12"]
    assert result["views_per_object"] == 4 and len(result["objects"]) == 2 and result["checkpoint_step"] == 7
    assert result["guide_depth"] == "prior aligned to a coarse render" and result["depth_prior"] == "oracle"

    session = InferenceSession(weights, SessionOptions(inputs="dataset", data_root=root))
    summary = evaluate_protocol(session, tmp_path / "eval", ProtocolConfig(views_stride=20, max_objects=2, mesh=False,
                                                                           progress=False, choices=FLOAT)).summary
    ref = rows["reference"]
    assert summary["views"] == 2 * 4 and ref["views"] == 8
    assert ref["psnr"] == pytest.approx(summary["psnr"], abs=1e-4)
    assert ref["ssim"] == pytest.approx(summary["ssim"], abs=1e-5)
    for mine, theirs in zip(ref["per_object"], summary["per_object"], strict=True):
        assert mine["object_id"] == theirs["object_id"] and mine["psnr"] == pytest.approx(theirs["psnr"], abs=1e-4)

    assert ref["evals_per_ray"] == 6 + (6 + 4 + 2) and ref["speedup"] == 1.0 and ref["psnr_delta"] == 0.0
    assert ref["samples_per_ray"] == "6+4+2" and ref["psnr_vs_reference"] is None and not ref["meets_target"]
    for name, occupied, empty in (("guided-6", 6, 3), ("guided-12", 12, 6)):
        row = rows[name]
        assert empty < row["evals_per_ray"] < occupied  # both occupied and empty rays were rendered
        assert row["psnr_delta"] == pytest.approx(row["psnr"] - ref["psnr"], abs=1e-9)
        assert row["speedup"] == pytest.approx(ref["ms_per_view"] / row["ms_per_view"])
        assert row["meets_target"] == (row["speedup"] >= 3 and row["psnr_delta"] >= -0.1)
        assert 0 < row["psnr_vs_reference"] <= 100


def test_guided_budget_split(bench):
    """One budget sets the sampler's counts of the one guided config; the default counts are the default budget's."""
    from guided_checkpoint import guided_config

    g = guided_config(8)
    assert (g.enabled, g.n_uniform, g.n_window, g.n_importance, g.n_gaussian) == (True, 1, 3, 3, 1)
    assert (g.n_empty, g.n_empty_importance) == (3, 1)
    default = GuidedConfig()
    assert dataclasses.replace(guided_config(DEFAULT_BUDGET), enabled=False) == default
    assert default.budget == DEFAULT_BUDGET == 48
    for total in (6, 7, 16, 24, 31):
        g = guided_config(total, 5, GuidedConfig(spread=0.2))
        assert g.n_uniform + g.n_window + g.n_importance + g.n_gaussian == g.budget == total
        assert g.n_empty + g.n_empty_importance == total // 2 and (g.align_samples, g.spread) == (5, 0.2)
    with pytest.raises(DepthnerfError, match="--guided 5: a guided budget needs >= 6"):
        guided_config(5)


def test_reference_samples_override(bench, tmp_path):
    """``--reference-samples C,I,G`` renders the reference row with that sampler on the same network, and
    ``--plain-samplers`` adds unguided rows: network evaluations per ray are C + (C + I + G); guided rows report
    which fraction of rays the guide covered; a malformed value is a one-line error, exit 2."""
    root = make_srn_fixture(tmp_path / "data", "cars", {"test": 1}, views=66, size=16, with_depth=True,
                            with_mask=True)
    weights = tiny_checkpoint(tmp_path / "tiny.safetensors")
    out = tmp_path / "bench.json"
    common = ["--checkpoint", str(weights), "--data", str(root), "--objects", "1", "--views-stride", "40",
              "--budgets", "6", "--repeats", "1"]
    assert bench.main([*common, "--reference-samples", "8,4,4", "--plain-samplers", "4,2,2", "--json",
                       str(out)]) == 0
    result = json.loads(out.read_text())
    ref, plain, guided = result["rows"]
    assert result["reference_sampler"] == ref["samples_per_ray"] == "8+4+4"
    assert ref["evals_per_ray"] == 8 + (8 + 4 + 4) and ref["guide_valid_fraction"] is None
    assert plain["name"] == "plain-4+2+2" and plain["evals_per_ray"] == 4 + (4 + 2 + 2)
    assert not plain["guided"] and not plain["meets_target"] and 0 < plain["psnr_vs_reference"] <= 100
    assert 0 <= guided["guide_valid_fraction"] <= guided["guide_occupied_fraction"] <= 1
    assert bench.main([*common, "--reference-samples", "64,16"]) == 2


def test_eval_guided_matches_the_benchmark_row(bench, tmp_path):
    """``depthnerf eval --guided B`` and the benchmark's guided-B row run the same package code
    (depthnerf.render.source_guide): same prior alignment, same guide, same sampler, so the same PSNR."""
    from depthnerf.render.source_guide import guided_config

    root, weights, result = run_checkpoint_bench(bench, tmp_path, "12")
    row = {r["name"]: r for r in result["rows"]}["guided-12"]
    cfg = ProtocolConfig(views_stride=20, max_objects=2, mesh=False, progress=False,
                         choices=FLOAT)
    session = InferenceSession(weights, SessionOptions(inputs="dataset", data_root=root, guided=guided_config(12)))
    summary = evaluate_protocol(session, tmp_path / "eval", cfg).summary
    assert summary["guided_sampling"]["budget"] == 12 and "guided sampling (12/ray)" in summary["method"]
    assert row["psnr"] == pytest.approx(summary["psnr"], abs=1e-3)
    for mine, theirs in zip(row["per_object"], summary["per_object"], strict=True):
        assert mine["psnr"] == pytest.approx(theirs["psnr"], abs=1e-3)
