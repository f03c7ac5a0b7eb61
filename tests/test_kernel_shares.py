"""``benchmarks/kernel_shares.py`` against lease 7's profile of a compiled view (docs/gpu/h200_profile_view_compiled.txt):
its device-side kernels, by kind, give the split docs/speed.md states (42% element-wise, 30% matrix products, 21%
the ``grid_sample`` gather)."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))
from kernel_shares import kernel_kind, shares_of  # noqa: E402

UNITS = {"us": 1.0, "ms": 1e3, "s": 1e6}


def device_kernels(table: str) -> list[tuple[str, float]]:
    """(name, self CUDA time in us) of the table's device-side rows: a CUDA kernel has no CPU time of its own, and
    each appears once (the profiler also lists it under the launching op, with CPU time)."""
    rows = []
    for line in table.splitlines():
        cells = re.split(r"\s{2,}", line.strip())
        if len(cells) != 11 or cells[2] != "0.000us" or (cells[6].endswith("us") and float(cells[6][:-2]) == 0):
            continue
        value, unit = re.fullmatch(r"([\d.]+)(us|ms|s)", cells[6]).groups()
        rows.append((cells[0], float(value) * UNITS[unit]))
    return list(dict.fromkeys(rows))  # the table prints some kernels twice (under their op and alone)


def test_lease_7_view_profile_splits_as_docs_say():
    table = (ROOT / "docs" / "gpu" / "h200_profile_view_compiled.txt").read_text()
    kernels = device_kernels(table)
    assert len(kernels) >= 10
    shares = shares_of(kernels)  # of the table's top rows; docs/speed.md's shares are of all the GPU time
    total_ms = float(re.search(r"Self CUDA time total: ([\d.]+)s", table).group(1)) * 1e3
    assert shares["triton_pointwise"]["ms"] / total_ms == pytest.approx(0.42, abs=0.005)
    assert shares["matmul"]["ms"] / total_ms == pytest.approx(0.30, abs=0.005)
    assert shares["grid_sample"]["ms"] / total_ms == pytest.approx(0.21, abs=0.005)
    assert list(shares)[:3] == ["triton_pointwise", "matmul", "grid_sample"]  # kinds by time
    assert sum(v["share"] for v in shares.values()) == pytest.approx(1.0)


@pytest.mark.parametrize("name, kind", [
    ("nvjet_sm90_tst_256x128_64x4_1x2_h_bz_coopA_bias_TNT", "matmul"),
    ("sm90_xmma_gemm_bf16bf16_bf16f32_f32_tn_n_tilesize128x128x64", "matmul"),
    ("triton_tem_fused_addmm_relu_3", "matmul"),
    ("triton_poi_fused__to_copy_add_clamp_min_index_mul_8", "triton_pointwise"),
    ("triton_red_fused_sum_2", "triton_reduction"),
    ("void at::native::(anonymous namespace)::grid_sampler_2d_kernel<float, long>(...)", "grid_sample"),
    ("void at::native::(anonymous namespace)::CatArrayBatchedCopy<...>", "copy_cat"),
    ("void at::native::vectorized_elementwise_kernel<4, at::native::AddFunctor<float>, ...>", "elementwise_aten"),
    ("ncclDevKernel_AllReduce_Sum_f32_RING_LL", "other"),
])
def test_kernel_kinds_by_name(name, kind):
    assert kernel_kind(name) == kind
