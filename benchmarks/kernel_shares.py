"""Where a profiled call's GPU time goes, by kind of kernel: the split docs/speed.md reads off each view profile.

``kernel_shares`` sums the device time of the CUDA kernels a ``torch.profiler`` run recorded into kinds, from the
kernel's name:

* ``matmul``: cuBLAS / cuBLASLt / CUTLASS products (``gemm``, ``nvjet``, ``cutlass``, ``xmma``) and inductor's Triton
  matrix-product templates (``triton_tem``);
* ``grid_sample``: ``grid_sampler`` kernels (the feature gather before the MLP call);
* ``embedding_bag``: the fused gather of training and eager CPU-style calls;
* ``triton_pointwise``: inductor's fused element-wise kernels (``triton_poi``; with ``--gather inside`` they also
  read the feature maps);
* ``triton_reduction``: inductor's reductions (``triton_red``, ``triton_per``);
* ``copy_cat``: copies, concatenations and casts (``copy``, ``cat``, ``CatArray``);
* ``elementwise_aten``: eager ATen element-wise kernels (``elementwise_kernel``, ``vectorized_elementwise``);
* ``other``: the rest.

    from kernel_shares import kernel_shares, profile_table
    shares = kernel_shares(prof)      # {kind: {"ms": ..., "share": ...}}, kinds by GPU time
    shares = profile_table(fn, "profile.txt")   # profile one fn() call: the operator table, and the shares
"""

from __future__ import annotations

from collections.abc import Iterable

KINDS = (
    ("matmul", ("gemm", "nvjet", "cutlass", "xmma", "triton_tem")),
    ("grid_sample", ("grid_sampler",)),
    ("embedding_bag", ("embedding_bag", "EmbeddingBag")),
    ("triton_pointwise", ("triton_poi",)),
    ("triton_reduction", ("triton_red", "triton_per")),
    ("copy_cat", ("copy", "CatArray", "cat_")),
    ("elementwise_aten", ("elementwise_kernel", "vectorized_elementwise")),
)
"""Kinds in the order a name is tried against them: the first whose any marker the name holds wins."""


def kernel_kind(name: str) -> str:
    """The kind (:data:`KINDS`, else ``"other"``) of a CUDA kernel's name."""
    for kind, markers in KINDS:
        if any(marker in name for marker in markers):
            return kind
    return "other"


def shares_of(kernels: Iterable[tuple[str, float]]) -> dict[str, dict[str, float]]:
    """``{kind: {"ms", "share"}}`` of ``(kernel name, device time in microseconds)`` pairs, kinds by time."""
    totals: dict[str, float] = {}
    for name, us in kernels:
        kind = kernel_kind(name)
        totals[kind] = totals.get(kind, 0.0) + us
    whole = sum(totals.values())
    return {kind: {"ms": us / 1e3, "share": us / whole if whole else 0.0}
            for kind, us in sorted(totals.items(), key=lambda kv: -kv[1])}


def kernel_shares(prof) -> dict[str, dict[str, float]]:
    """:func:`shares_of` the CUDA kernels of a finished ``torch.profiler.profile`` (its device-side events)."""
    from torch.autograd import DeviceType

    return shares_of((evt.name, evt.device_time_total) for evt in prof.events()
                     if evt.device_type == DeviceType.CUDA)


def profile_table(fn, path: str, rows: int = 30) -> dict[str, dict[str, float]]:
    """Write ``torch.profiler``'s operator table of one ``fn()`` call, by CUDA time, to ``path``; return its GPU
    time by kind of kernel (``kernel_shares``)."""
    import torch
    from torch.profiler import ProfilerActivity, profile

    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        fn()
        torch.cuda.synchronize()
    with open(path, "w") as f:
        f.write(prof.key_averages().table(sort_by="cuda_time_total", row_limit=rows))
    shares = kernel_shares(prof)
    print(f"profile: {path}; GPU time by kind: "
          + ", ".join(f"{kind} {v['ms']:.1f} ms ({v['share']:.0%})" for kind, v in shares.items()))
    return shares
