"""How the field MLPs' inference settings trade speed for accuracy: prints figures, asserts nothing.

A paper-sampler view is bound by the MLPs' memory traffic, not their matrix products (docs/speed.md, "GPU"): the
fp32 residual stream is read and written around every bf16 linear, and the features are gathered by
``grid_sample`` before the compiled MLP. Three opt-in settings cut that traffic (:mod:`depthnerf.render.precision`):
``--bf16-residual`` keeps the stream in bf16, ``--compile-mode max-autotune-no-cudagraphs`` lets inductor fuse
the element-wise work into Triton matrix products, and ``--gather inside`` / ``inside-bf16`` moves the gather into
the compiled MLP forward (from fp32 / bf16 maps). ``triton-mm+inside-bf16`` (:data:`INDUCTOR_OPTIONS`, no CLI
flag) makes every linear a Triton template with the element-wise work fused into it;
``compiled+inside-bf16+relu-ep`` (:data:`RUNTIME_FIELDS`) also runs each block's first bias and ReLU in the
cuBLASLt matrix product's epilogue (``FieldRuntime.relu_epilogue``).

Speed (CUDA; the paper preset's MLPs with seeded random weights, one synthetic source view, 128x128 views, as
``benchmarks/bench_gpu.py``): ms per view for each variant, and how far its renders are from the fp32 renders of
the same weights (largest absolute colour difference, and the PSNR between the two):

    python benchmarks/bench_view_variants.py --json out.json                       # every variant
    python benchmarks/bench_view_variants.py --variants eager eager+bf16res

Accuracy on a trained model (any device; on the CPU bf16 autocast runs in software): ``depthnerf eval``'s protocol
on a checkpoint's test objects under fp32, bf16 autocast (CUDA's default) and bf16 autocast with a bf16 residual
stream, and the per-object PSNR differences against fp32:

    python benchmarks/bench_view_variants.py --checkpoint cpu-cars-sym-pp --data DIR --objects 10
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "scripts"))
from bench_gpu import synthetic_batch, timed, view_source  # noqa: E402
from paired_difference import read_per_object  # noqa: E402

from depthnerf.data.cameras import look_at  # noqa: E402
from depthnerf.render.precision import InferencePolicy, field_runtime, inference_policy  # noqa: E402

VARIANTS = {
    "eager": {},
    "compiled": {"compile": True},
    "compiled+inside": {"compile": True, "gather": "inside"},
    "compiled+inside-bf16": {"compile": True, "gather": "inside-bf16"},
    "compiled+inside-bf16+relu-ep": {"compile": True, "gather": "inside-bf16"},
    "eager+bf16res": {"bf16_residual": True},
    "compiled+bf16res": {"compile": True, "bf16_residual": True},
    "autotuned+bf16res": {"compile_mode": "max-autotune-no-cudagraphs", "bf16_residual": True},
    "autotuned": {"compile_mode": "max-autotune-no-cudagraphs"},
    "triton-mm+inside-bf16": {"gather": "inside-bf16"},
}
"""Speed variants, in the default order: name -> :func:`~depthnerf.render.precision.inference_policy` flags (all
under bf16 autocast; ``eager`` and ``compiled`` are what ``eval`` / ``reconstruct`` run without and with
``--compile``). Variants in :data:`INDUCTOR_OPTIONS` compile with those inductor options instead of a mode."""
RUNTIME_FIELDS = {
    "compiled+inside-bf16+relu-ep": {"relu_epilogue": True},
}
"""Benchmark-only variants (no CLI flag): :class:`~depthnerf.model.pixelnerf.FieldRuntime` fields set on top of
the policy's runtime (``relu_epilogue``: each block's first bias and ReLU in the matrix product's epilogue)."""
INDUCTOR_OPTIONS = {
    "triton-mm+inside-bf16": {"max_autotune": True, "max_autotune_gemm_backends": "TRITON", "epilogue_fusion": True},
}
"""Benchmark-only variants (no CLI flag): ``torch.compile(options=...)``. ``TRITON`` as the only matrix-product
backend makes every linear a Triton template, into which inductor fuses the element-wise work around it (bias,
ReLU, residual add, casts, the gather's reads inside the forward); ``max-autotune`` alone may keep cuBLAS, which fuses none."""


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    """PSNR of ``a`` against ``b`` (values in [0, 1])."""
    mse = float(((a.float() - b.float()) ** 2).mean())
    return math.inf if mse == 0 else -10 * math.log10(mse)


def speed(args, out: dict, save: Callable[[], None]) -> None:
    """The speed variants (``save`` writes ``out`` after each, so a run stopped from outside keeps them)."""
    from depthnerf.model import PixelNeRF
    from depthnerf.render.views import render_poses
    from depthnerf.train.config import preset, with_prior

    device = torch.device(args.device or "cuda")
    cfg = with_prior(preset("paper-cars"), "none")
    torch.manual_seed(0)
    model = PixelNeRF(cfg.model, depth_aware=False).to(device).eval()
    model.encoder.to(memory_format=torch.channels_last)
    with torch.no_grad():  # pixelNeRF zero-initialises each block's second linear: give the blocks work to do
        for mlp in (model.coarse, model.fine):
            for block in mlp.blocks:
                block.fc_1.weight.normal_(0, 0.5 / math.sqrt(block.fc_1.in_features))
    batch, intr = synthetic_batch(1, 8, args.resolution, depth_aware=False)
    batch = batch.to(device)
    az = torch.linspace(0, 2 * math.pi, args.views + 1)[:-1]
    poses = look_at(torch.stack([1.2 * torch.cos(az), 1.2 * torch.sin(az), torch.full_like(az, 0.5)], -1))
    out.update(device=str(device), gpu=torch.cuda.get_device_name(device) if device.type == "cuda" else None,
               torch=torch.__version__, resolution=args.resolution,
               views_per_call=args.views, variants={})
    t_start = time.perf_counter()
    with torch.no_grad():
        enc = model.encode(view_source(batch))

        def render(policy: InferencePolicy, options: dict | None = None, fields: dict | None = None
                   ) -> tuple[Callable[[], object], torch.Tensor]:
            runtime = dataclasses.replace(field_runtime(model, policy), **(fields or {}))
            if options is not None:
                compiled = {id(m): torch.compile(m.forward, dynamic=True, options=options)
                            for m in (model.coarse, model.fine)}
                runtime = dataclasses.replace(runtime, forwards={w: compiled[id(model.network(w))]
                                                                 for w in ("coarse", "fine")})

            def call():
                return render_poses(model, enc, poses, intr, 0.8, 1.8, cfg.render, policy.ray_chunk, device,
                                    runtime=runtime)
            return call, call().rgb

        # CUDA's policies wherever this runs (on a CPU: a smoke test of the variants, bf16 autocast in software)
        _, reference = render(inference_policy("cuda", fp32=True))
        for name in args.variants:
            row = out["variants"][name] = {"flags": VARIANTS[name], "inductor_options": INDUCTOR_OPTIONS.get(name),
                                           "runtime_fields": RUNTIME_FIELDS.get(name)}
            if time.perf_counter() - t_start > args.budget_s:
                row["skipped"] = f"the --budget-s of {args.budget_s} s was spent"
                print(f"{name:18s} skipped: budget spent")
                save()
                continue
            torch._dynamo.reset()
            t0 = time.perf_counter()
            call, rgb = render(inference_policy("cuda", **VARIANTS[name]), INDUCTOR_OPTIONS.get(name),
                               RUNTIME_FIELDS.get(name))
            call()  # torch.compile(dynamic=True) may recompile on the second call's shapes
            if device.type == "cuda":
                torch.cuda.synchronize()
            row["warmup_s"] = time.perf_counter() - t0
            t = timed(call, args.repeat, device)
            row.update(ms_per_view=min(t) / args.views * 1e3, ms_per_view_median=statistics.median(t) / args.views * 1e3,
                       max_abs_diff_vs_fp32=float((rgb.float() - reference.float()).abs().max()),
                       psnr_vs_fp32=psnr(rgb, reference))
            print(f"{name:18s} {row['ms_per_view']:7.1f} ms per view (median {row['ms_per_view_median']:.1f}; "
                  f"warm-up {row['warmup_s']:.0f} s); against fp32: max |diff| {row['max_abs_diff_vs_fp32']:.4f}, "
                  f"PSNR {row['psnr_vs_fp32']:.1f} dB")
            save()


def accuracy(args, out: dict) -> None:
    from depthnerf.eval.config import ProtocolConfig
    from depthnerf.eval.protocol import evaluate_protocol
    from depthnerf.infer.session import InferenceSession, SessionOptions

    device = torch.device(args.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    own = inference_policy(device)  # the device's chunks; the precision is what varies
    policies = {
        "fp32": dataclasses.replace(own, autocast=None),
        "bf16": dataclasses.replace(own, autocast=torch.bfloat16),
        "bf16+bf16res": dataclasses.replace(own, autocast=torch.bfloat16, residual=torch.bfloat16),
    }
    cfg = ProtocolConfig(views_stride=args.views_stride, max_objects=args.objects, mesh=False, progress=False)
    per_object: dict[str, dict[str, float]] = {}
    out.update(checkpoint=args.checkpoint, device=device.type, objects=args.objects, views_stride=args.views_stride,
               psnr={}, seconds={})
    with tempfile.TemporaryDirectory() as tmp:
        for name, policy in policies.items():
            session = InferenceSession(args.checkpoint, SessionOptions(device=device, inputs="dataset",
                                                                       data_root=args.data, policy=policy))
            t0 = time.perf_counter()
            result = evaluate_protocol(session, Path(tmp) / name, cfg)
            out["seconds"][name] = time.perf_counter() - t0
            per_object[name] = {k: float(row["psnr"]) for k, row in read_per_object(Path(tmp) / name).items()}
            out["psnr"][name] = result.summary["psnr"]
            print(f"{name:13s} PSNR {result.summary['psnr']:.4f} ({out['seconds'][name]:.0f} s)")
    for name in ("bf16", "bf16+bf16res"):
        diffs = [per_object[name][k] - per_object["fp32"][k] for k in per_object["fp32"]]
        out[f"{name}_minus_fp32"] = {"mean": statistics.fmean(diffs), "largest_abs": max(map(abs, diffs))}
        print(f"{name} - fp32, per object: mean {statistics.fmean(diffs):+.4f} dB, largest |difference| "
              f"{max(map(abs, diffs)):.4f} dB ({len(diffs)} objects)")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=list(VARIANTS),
                   help="speed variants, in order (default: all)")
    p.add_argument("--views", type=int, default=16, help="views per render call (speed)")
    p.add_argument("--resolution", type=int, default=128, help="view size (speed)")
    p.add_argument("--repeat", type=int, default=5, help="timed calls per variant (speed)")
    p.add_argument("--budget-s", type=float, default=240.0,
                   help="speed: variants that would start after this many seconds are skipped (each compiles first)")
    p.add_argument("--checkpoint", help="accuracy: a trained checkpoint (shipped name or path)")
    p.add_argument("--data", type=Path, help="accuracy: the dataset its test objects come from")
    p.add_argument("--objects", type=int, default=10, help="accuracy: test objects (default 10)")
    p.add_argument("--views-stride", type=int, default=25, help="accuracy: every K-th target view (default 25)")
    p.add_argument("--device", help="cuda or cpu (default: CUDA when available, else the CPU). The speed variants "
                                     "run on the CPU only when it is named (a smoke test: slow, not comparable)")
    p.add_argument("--json", metavar="PATH", help="also write the figures to PATH as JSON")
    args = p.parse_args()
    out: dict = {}

    def save() -> None:
        if args.json:
            Path(args.json).write_text(json.dumps(out, indent=1))
    try:
        if args.checkpoint:
            if args.data is None:
                p.error("--checkpoint needs --data")
            accuracy(args, out)
        elif args.device is None and not torch.cuda.is_available():
            print("bench_view_variants: the speed variants need CUDA; on this machine run the accuracy part "
                  "(--checkpoint NAME --data DIR)")
            out["skipped"] = "no CUDA"
        else:
            speed(args, out, save)
    except BaseException as e:  # the figures so far still go to --json, with what stopped the run
        out["error"] = f"{type(e).__name__}: {e}"
        raise
    finally:
        save()


if __name__ == "__main__":
    main()
