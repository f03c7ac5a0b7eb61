"""``benchmarks/bench_gpu.py``'s FLOP count of one view against the closed form: every ray evaluates the coarse
field at ``n_coarse`` points and the fine field at ``n_coarse + n_importance + n_gaussian``, and each point costs
2 FLOPs per multiply-add of the field's per-point linears (``lin_in``, two per residual block, ``lin_out``); the
``lin_z`` projections run once per render call on every feature-map pixel. Left out of the closed form: the
camera transforms (small batched products on every point, far below 50 FLOPs a point)."""

from __future__ import annotations

import dataclasses
import importlib.util
import sys
from pathlib import Path

import torch

from depthnerf.model.pixelnerf import PixelNeRF
from depthnerf.train.config import preset, with_prior

BENCH = Path(__file__).resolve().parent.parent / "benchmarks" / "bench_gpu.py"


def _bench():
    sys.path.insert(0, str(BENCH.parent))
    try:
        spec = importlib.util.spec_from_file_location("bench_gpu", BENCH)
        module = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = module
        spec.loader.exec_module(module)
        return module
    finally:
        sys.path.remove(str(BENCH.parent))


def _per_point(field: torch.nn.Module) -> int:
    linears = [field.lin_in, *[fc for b in field.blocks for fc in (b.fc_0, b.fc_1)], field.lin_out]
    return sum(2 * fc.in_features * fc.out_features for fc in linears)


def test_view_flops_equal_the_closed_form() -> None:
    bench = _bench()
    cfg = with_prior(preset("cpu-cars"), "none")
    torch.manual_seed(0)
    model = PixelNeRF(cfg.model, depth_aware=False).eval()
    batch, intr = bench.synthetic_batch(1, 8, 16, False)
    intr = dataclasses.replace(intr, height=6, width=5)  # 30 rays
    with torch.no_grad():
        enc = model.encode(bench.view_source(batch))
    pose = bench.look_at(torch.tensor([[1.2, 0.0, 0.5]]))
    got = bench.view_gflop(model, enc, pose, intr, cfg, torch.device("cpu")) * 1e9
    sc = cfg.render.sampler
    want = 30 * (sc.n_coarse * _per_point(model.coarse)
                 + (sc.n_coarse + sc.n_importance + sc.n_gaussian) * _per_point(model.fine))
    _, _, channels, hf, wf = enc.features.shape
    want += sum(len(f.lin_z) * 2 * channels * f.lin_z[0].out_features * hf * wf for f in (model.coarse, model.fine))
    points = 30 * (2 * sc.n_coarse + sc.n_importance + sc.n_gaussian)
    assert want <= got <= want + 50 * points
