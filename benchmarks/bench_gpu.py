"""GPU speed of the paper preset (issue 12): prints figures, asserts nothing.

On CUDA it prints: ms per training iteration (bf16 autocast, fused Adam, the batched step), CUDA kernel launches
per step (``torch.profiler``), peak GPU memory, and ms per 128x128 novel view with the paper's sampler and with
depth-guided sampling (a synthetic source depth builds the guide; the view's cost, not its accuracy).

On a CPU-only machine it runs the same paper-preset training step on the CPU and its LAST line reads
``aten ops per training step: N``: the aten operators dispatched by one step (forward, backward, optimiser),
counted with a ``TorchDispatchMode`` while the step is composed as on CUDA (bf16 autocast, fused Adam; the
legacy loop with torch's CUDA default, foreach Adam), the proxy for CUDA kernel launches. ``--step-shape per-object`` counts the
earlier one-object-at-a-time step; run against a checkout without ``depthnerf.train.step`` it counts that
checkout's loop body (the "before" figure of docs/speed.md).

    python benchmarks/bench_gpu.py                       # CUDA if available, else the CPU op count
    python benchmarks/bench_gpu.py --device cpu --time   # also time the CPU step (~10 s per iteration)
    python benchmarks/bench_gpu.py --json out.json       # also write the figures as JSON (scripts/gpu_check.py)
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from kernel_shares import profile_table  # noqa: E402
from op_count import CountOps  # noqa: E402

from depthnerf.data.cameras import Intrinsics, look_at
from depthnerf.model import PixelNeRF, SourceViews
from depthnerf.render.rays import rays_from_camera
from depthnerf.train.batching import ItemKey, TrainBatch
from depthnerf.train.config import preset, with_prior

SRN_EVAL_VIEWS = 704 * 250
"""The SRN-protocol cars test set: 704 objects x 250 target views (the projection of the per-view figures)."""


def synthetic_batch(b: int, rays: int, res: int, depth_aware: bool, seed: int = 0) -> tuple[TrainBatch, Intrinsics]:
    """Random source images on the SRN cars camera sphere and random target rays (timing only)."""
    gen = torch.Generator().manual_seed(seed)
    intr = Intrinsics(focal=131.25 * res / 128, cx=(res - 1) / 2, cy=(res - 1) / 2, height=res, width=res)
    az = torch.rand(b, 2, generator=gen) * 2 * math.pi
    eye = torch.stack([1.2 * torch.cos(az), 1.2 * torch.sin(az), torch.full_like(az, 0.5)], -1)
    poses = look_at(eye)
    all_rays = rays_from_camera(poses[:, 1], intr, 0.8, 1.8)
    idx = torch.randint(0, all_rays.num_rays, (b, rays), generator=gen)
    pick = [torch.gather(t, 1, idx[..., None].expand(-1, -1, 3)) for t in (all_rays.origins, all_rays.directions)]
    src = dict(images=torch.rand(b, 1, 3, res, res, generator=gen), poses=poses[:, :1],
               focal=torch.full((b,), intr.focal), principal=torch.full((b, 2), intr.cx),
               disparity=torch.randn(b, 1, 1, res, res, generator=gen) if depth_aware else None)
    if any(f.name == "source" for f in dataclasses.fields(TrainBatch)):
        src = {"source": SourceViews(**src)}
    else:  # a checkout from before TrainBatch carried the conditioning stage's SourceViews
        src = {k if k in ("focal", "principal") else f"src_{k}": v for k, v in src.items()}
    batch = TrainBatch(**src,
                       ray_origins=pick[0], ray_dirs=pick[1], target_rgb=torch.rand(b, rays, 3, generator=gen),
                       target_prior=None, target_fg=torch.rand(b, rays, generator=gen) > 0.5,
                       target_cos=torch.ones(b, rays))
    return batch, intr


def make_step(model: PixelNeRF, cfg, batch: TrainBatch, device: torch.device, step_shape: str, as_cuda: bool,
              compile: bool = False, compile_step: bool = False):
    """One optimisation step as the training loop runs it on ``device``; with ``as_cuda`` composed as on CUDA
    (bf16 autocast, fused Adam) whatever the device: the CPU op-count proxy; ``compile``: as ``depthnerf train
    --compile`` runs it (the fields' MLPs through ``torch.compile``); ``compile_step``: as ``--compile-step`` (the
    whole loss as one compiled graph, CUDA graphs on CUDA)."""
    cuda = device.type == "cuda" or as_cuda
    amp = torch.autocast(device.type, dtype=torch.bfloat16) if cuda else contextlib.nullcontext()
    keys = [ItemKey(k, 1000 + k, True) for k in range(batch.ray_origins.shape[0])]
    try:
        from depthnerf.train.step import BatchLoss, train_step
    except ImportError:  # a checkout from before the batched step: its loop body, verbatim in shape
        return legacy_step(model, cfg, batch, device, keys, amp, cuda)
    opt = torch.optim.Adam(model.parameters(), lr=1e-4, fused=cuda or None)
    runtime = None
    if compile:
        from depthnerf.train.step import compiled_fields
        runtime = compiled_fields(model)
    backend = ("inductor",) if compile_step else ()  # passed only when asked: older checkouts lack the argument
    loss = BatchLoss(model, cfg.render, 0.0, 0.0, runtime, *backend)

    def step():
        opt.zero_grad(set_to_none=True)
        train_step(loss, batch, keys, 0, 0.8, 1.8, device, amp=amp, per_object=step_shape == "per-object")
        opt.step()
    return step


def legacy_step(model, cfg, batch, device, keys, amp, cuda: bool):
    from depthnerf.train.batching import item_seed
    from depthnerf.train.loop import ObjectLoss  # exists only before the batched step

    opt = torch.optim.Adam(model.parameters(), lr=1e-4, foreach=cuda or None)  # torch's default on CUDA: foreach
    runner = ObjectLoss(model, cfg.render, 0.0, 0.0)

    def step():
        opt.zero_grad(set_to_none=True)
        sums = torch.zeros(5, dtype=torch.float64)
        for k, key in enumerate(keys):
            gen = torch.Generator(device).manual_seed(item_seed(key.seed, 0, 1))
            with amp:
                terms = runner(batch.item(k), 0.8, 1.8, gen)
                (terms.total / len(keys)).backward()
            sums += torch.tensor([float(t.detach()) for t in (terms.total, terms.coarse, terms.fine, terms.depth,
                                                              terms.background)], dtype=torch.float64)
        opt.step()
    step.shape = "legacy per-object (this checkout's loop body)"
    return step


def timed(fn, repeat: int, device: torch.device) -> list[float]:
    out = []
    for _ in range(repeat):
        if device.type == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize()
        out.append(time.perf_counter() - t0)
    return out


HOST_LAUNCH_CALLS = ("cudaLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernel", "cuLaunchKernelEx",
                     "cudaGraphLaunch", "cudaMemcpyAsync", "cudaMemsetAsync")
"""CUDA runtime/driver calls by which the host starts work on the GPU (as the profiler names them)."""


def cuda_launches(fn) -> tuple[int, int]:
    """Of one ``fn()`` call: the work items the GPU ran (kernels and copies, also those inside CUDA graphs) and
    the host's launch calls (:data:`HOST_LAUNCH_CALLS`: a replayed CUDA graph is one call for all its kernels)."""
    from torch.profiler import ProfilerActivity, profile

    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        fn()
        torch.cuda.synchronize()
    events = prof.events()
    device = sum(1 for e in events if e.device_type == torch.autograd.DeviceType.CUDA)
    host = sum(1 for e in events if e.device_type == torch.autograd.DeviceType.CPU and e.name in HOST_LAUNCH_CALLS)
    return device, host


def view_source(batch: TrainBatch) -> SourceViews:
    """The first object's source view of a training batch (older checkouts' batches had no ``item``)."""
    if hasattr(batch, "item"):
        return batch.item(0).source
    return SourceViews(batch.src_images[:1], batch.src_poses[:1], batch.focal[:1], batch.principal[:1],
                       batch.src_prior[:1] if batch.src_prior is not None else None)


def view_timings(model: PixelNeRF, cfg, batch: TrainBatch, intr: Intrinsics, device: torch.device, views: int,
                 repeat: int, out: dict, compile: bool = False, profile_dir: str | None = None,
                 gather: str = "before") -> None:
    """Print (and put in ``out``) ms per view with the paper's sampler and guided, and the SRN eval projection
    (``compile``: the field MLPs through ``torch.compile``; ``profile_dir``: also profile one paper-sampler call;
    ``gather``: where the features are gathered, ``--gather``)."""
    from depthnerf.render.precision import field_runtime, inference_policy
    from depthnerf.render.views import render_poses, render_views, view_rays

    model.eval()
    policy = inference_policy(device, compile=compile, gather=gather)
    out["view_compile"], out["view_gather"] = compile, gather
    runtime = field_runtime(model, policy)
    src = view_source(batch)
    az = torch.linspace(0, 2 * math.pi, views + 1)[:-1]
    poses = look_at(torch.stack([1.2 * torch.cos(az), 1.2 * torch.sin(az), torch.full_like(az, 0.5)], -1))
    with torch.no_grad():
        enc = model.encode(src)

        def paper():
            render_poses(model, enc, poses, intr, 0.8, 1.8, cfg.render, policy.ray_chunk, device, runtime=runtime)
        paper()
        if compile:
            paper()  # torch.compile(dynamic=True) may recompile on the second call's shapes
        t = timed(paper, repeat, device)
        if profile_dir:
            shares = profile_table(paper, f"{profile_dir}/profile_view{'_compiled' if compile else ''}.txt")
            out["view_profile_ms_per_view"] = {kind: v["ms"] / views for kind, v in shares.items()}
        print(f"view  paper sampler 64+16+16, {intr.height}x{intr.width}, {views} views per call, chunk "
              f"{policy.ray_chunk}, {'bf16' if policy.autocast else 'fp32'}: {min(t) / views * 1e3:.1f} ms per view")
        out.update(view_paper_ms=min(t) / views * 1e3, view_resolution=intr.height, views_per_call=views,
                   view_precision="bf16" if policy.autocast else "fp32")
        project(out, "paper", out["view_paper_ms"])
        gflop = paper_view_gflop(model, cfg, intr.height, device)
        out.update(view_paper_gflop=gflop, view_paper_tflops=gflop / out["view_paper_ms"])
        print(f"view  paper sampler: {gflop:.0f} GFLOP per view (matrix products, torch.utils.flop_counter), "
              f"{gflop / out['view_paper_ms']:.1f} TFLOP/s achieved")
        try:
            from depthnerf.render.config import GuidedConfig
            from depthnerf.render.depth_guide import build_depth_guide
        except ImportError:
            print("view  guided: N/A (no depth guide in this checkout)")
            out["view_guided_ms"] = None
            return
        gcfg = dataclasses.replace(cfg.render, guided=dataclasses.replace(cfg.render.guided, enabled=True))
        rays = view_rays(poses.to(device), intr, 0.8, 1.8)
        depth = torch.full((1, intr.height, intr.width), 1.2, device=device)  # a synthetic source surface
        mask = torch.zeros_like(depth, dtype=torch.bool)
        mask[:, intr.height // 4: 3 * intr.height // 4, intr.width // 4: 3 * intr.width // 4] = True
        guide = build_depth_guide(src.poses[:, 0].to(device), intr, depth, mask, rays, GuidedConfig())
        coarse, fine = model.field(enc, "coarse", runtime), model.field(enc, "fine", runtime)

        def guided():
            render_views(coarse, fine, poses.to(device), intr, 0.8, 1.8, gcfg, chunk=policy.ray_chunk * views,
                         guide=guide)
        guided()
        if compile:
            guided()
        t = timed(guided, repeat, device)
        print(f"view  guided sampler (synthetic guide, {guide.occupied.float().mean():.0%} rays occupied): "
              f"{min(t) / views * 1e3:.1f} ms per view")
        out.update(view_guided_ms=min(t) / views * 1e3, guided_rays_occupied=float(guide.occupied.float().mean()))
        project(out, "guided", out["view_guided_ms"])


def in_place_addmm_flop(self_shape, a_shape, b_shape, *_, **__) -> int:
    """FLOPs of ``self.addmm_(a, b)``: ``(n, k) @ (k, m)``, 2 per multiply-add (the bias add is not counted, as
    ``torch.utils.flop_counter`` does for ``addmm``)."""
    return 2 * a_shape[0] * a_shape[1] * b_shape[1]


def view_gflop(model: PixelNeRF, enc, poses: torch.Tensor, intr: Intrinsics, cfg, device: torch.device) -> float:
    """GFLOP of the paper-sampler views at ``poses`` as ``torch.utils.flop_counter`` counts them (2 per
    multiply-add of every matrix product and convolution; elementwise work is not counted), rendered eagerly with
    ``device``'s inference policy. The fields' in-place inference products (``addmm_``, which the counter does not
    know) are counted as ``addmm``."""
    from torch.utils.flop_counter import FlopCounterMode

    from depthnerf.render.precision import field_runtime, inference_policy
    from depthnerf.render.views import render_poses

    eager = inference_policy(device, compile=False)
    aten = torch.ops.aten
    counter = FlopCounterMode(display=False, custom_mapping={aten.addmm_: in_place_addmm_flop})
    with torch.no_grad(), counter:
        render_poses(model, enc, poses, intr, 0.8, 1.8, cfg.render, eager.ray_chunk, device,
                     runtime=field_runtime(model, eager))
    return counter.get_total_flops() / 1e9


def paper_view_gflop(model: PixelNeRF, cfg, resolution: int, device: torch.device) -> float:
    """GFLOP of one ``resolution`` x ``resolution`` paper-sampler view (:func:`view_gflop`), counted on a 16 x 16
    view of a synthetic source and scaled by the pixel count: every ray costs the same, and the feature map (whose
    ``lin_z`` products are counted once per view) scales with the image too."""
    training = model.training
    model.eval()
    batch, intr = synthetic_batch(1, 8, 16, model.depth_aware)
    with torch.no_grad():
        enc = model.encode(view_source(batch.to(device)))
    pose = look_at(torch.tensor([[1.2, 0.0, 0.5]]))
    gflop = view_gflop(model, enc, pose, intr, cfg, device)
    model.train(training)
    return gflop * (resolution / 16) ** 2


def project(out: dict, name: str, ms_per_view: float) -> None:
    """The SRN-protocol evaluation (704 x 250 views) projected from a per-view time, in GPU-hours."""
    hours = SRN_EVAL_VIEWS * ms_per_view / 1e3 / 3600
    out[f"eval_704x250_{name}_gpu_hours"] = hours
    print(f"eval projection, 704 objects x 250 views, {name} sampler: {hours:.2f} GPU-hours")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="auto", help="auto, cpu or cuda")
    p.add_argument("--objects", type=int, default=4, help="objects per step (paper: 4)")
    p.add_argument("--rays", type=int, default=128, help="rays per object (paper: 128)")
    p.add_argument("--resolution", type=int, default=128)
    p.add_argument("--depth", default="none", choices=["none", "bundled"], help="baseline or depth-aware encoder")
    p.add_argument("--step-shape", default="batched", choices=["batched", "per-object"])
    p.add_argument("--repeat", type=int, default=20, help="timed iterations on CUDA (CPU: with --time, 3)")
    p.add_argument("--views", type=int, default=16, help="views per render call on CUDA")
    p.add_argument("--time", action="store_true", help="on the CPU: also time the step (slow)")
    p.add_argument("--no-views", action="store_true", help="CUDA: training figures only")
    p.add_argument("--count-rays", type=int, default=8, help="CPU op count: rays per object (count is the same)")
    p.add_argument("--view-flops", action="store_true",
                   help="on the CPU: also count a paper-sampler view's FLOPs (on 16x16 rays, scaled to --resolution; "
                        "every ray costs the same)")
    p.add_argument("--breakdown", type=int, nargs="?", const=25, default=0, metavar="TOP",
                   help="CPU op count: also print it by phase, aten op, module and source (TOP rows each)")
    p.add_argument("--json", metavar="PATH", help="also write the printed figures to PATH as JSON")
    p.add_argument("--compile", action="store_true",
                   help="CUDA: the fields' MLPs through torch.compile, in the training step (as depthnerf train "
                        "--compile) and in the views (as eval / reconstruct --compile)")
    p.add_argument("--compile-step", action="store_true",
                   help="CUDA: the training step as depthnerf train --compile-step runs it (one compiled graph, "
                        "replayed as CUDA graphs); views stay eager unless --compile")
    p.add_argument("--gather", default="before", choices=["before", "inside", "inside-bf16"],
                   help="CUDA views: where the fields gather their features (as eval / reconstruct --gather)")
    p.add_argument("--profile", metavar="DIR", help="CUDA: write torch.profiler tables of one training step and one "
                   "paper-sampler view call to DIR/profile_{train,view}.txt")
    args = p.parse_args()
    out: dict = {}
    try:
        run(args, out)
    except BaseException as e:  # the figures so far still go to --json, with what stopped the run
        out["error"] = f"{type(e).__name__}: {e}"
        raise
    finally:
        if args.json:
            with open(args.json, "w") as f:
                json.dump(out, f, indent=1)


def run(args, out: dict) -> None:
    device = torch.device("cuda" if args.device == "auto" and torch.cuda.is_available() else
                          ("cpu" if args.device == "auto" else args.device))
    cfg = with_prior(preset("paper-cars"), args.depth)
    torch.manual_seed(0)
    depth_aware = args.depth != "none"
    try:
        model = PixelNeRF(cfg.model, depth_aware=depth_aware)
    except TypeError:  # older checkouts: the switch was named use_depth, and before that stored in the config
        try:
            model = PixelNeRF(cfg.model, use_depth=depth_aware)
        except TypeError:
            model = PixelNeRF(cfg.model)
    model = model.to(device).train()
    if device.type == "cuda":
        model.encoder.to(memory_format=torch.channels_last)
    batch, intr = synthetic_batch(args.objects, args.rays, args.resolution, depth_aware)
    batch = batch.to(device)
    step = make_step(model, cfg, batch, device, args.step_shape, as_cuda=False, compile=args.compile,
                     compile_step=args.compile_step)
    shape = getattr(step, "shape", args.step_shape)
    out.update(device=str(device), objects=args.objects, rays=args.rays, resolution=args.resolution,
               depth=args.depth, step_shape=shape, torch=torch.__version__, compile=args.compile,
               compile_step=args.compile_step)
    if device.type == "cuda":
        out.update(gpu=torch.cuda.get_device_name(device), cuda=torch.version.cuda)
        t0 = time.perf_counter()
        step()  # warm-up (allocations, cuDNN/cuBLAS handles; with --compile the compilation)
        if args.compile or args.compile_step:
            step()
            step()  # CUDA graphs record on the second call and replay from the third
            out["compile_warmup_s"] = time.perf_counter() - t0
            print(f"compilation: first three steps {out['compile_warmup_s']:.1f} s")
    print(f"paper preset ({cfg.model.encoder.backbone}, d_hidden {cfg.model.coarse.d_hidden}, "
          f"{cfg.render.sampler.n_coarse}+{cfg.render.sampler.n_importance}+{cfg.render.sampler.n_gaussian} "
          f"samples), {args.objects} objects x {args.rays} rays, {args.resolution} px, {shape} step, "
          f"device {device}")
    if device.type == "cuda":
        # the warm-up's peak too: CUDA graphs (--compile-step) allocate their memory pool while recording, so the
        # timed steps' peak alone leaves out what the step holds
        out["peak_memory_gib_warmup"] = torch.cuda.max_memory_allocated() / 2**30
        torch.cuda.reset_peak_memory_stats()
        t = timed(step, args.repeat, device)
        print(f"train iteration: {min(t) * 1e3:.1f} ms best, {statistics.median(t) * 1e3:.1f} ms median "
              f"({args.repeat} iterations)")
        out.update(train_ms_best=min(t) * 1e3, train_ms_median=statistics.median(t) * 1e3, repeat=args.repeat)
        out["kernel_launches_per_step"], out["host_launch_calls_per_step"] = cuda_launches(step)
        print(f"CUDA kernel launches per training step: {out['kernel_launches_per_step']} run on the GPU, "
              f"{out['host_launch_calls_per_step']} launch calls from the host")
        out["peak_memory_gib"] = torch.cuda.max_memory_allocated() / 2**30
        print(f"peak GPU memory (training): {out['peak_memory_gib']:.2f} GiB in the timed steps, "
              f"{out['peak_memory_gib_warmup']:.2f} GiB in the warm-up")
        if args.profile:
            out["train_profile_ms"] = {k: v["ms"] for k, v in
                                       profile_table(step, f"{args.profile}/profile_train.txt").items()}
        if not args.no_views:
            view_timings(model, cfg, batch, intr, device, args.views, max(3, args.repeat // 4), out, args.compile,
                         args.profile, args.gather)
        return
    if args.time:
        step()  # the untimed warm-up below is skipped without --time
        t = timed(step, 3, device)
        print(f"train iteration (CPU fp32): {min(t):.2f} s best, {statistics.median(t):.2f} s median")
        out.update(cpu_train_s_best=min(t), cpu_train_s_median=statistics.median(t))
    if args.view_flops:
        gflop = paper_view_gflop(model, cfg, args.resolution, device)
        print(f"view  paper sampler, {args.resolution}x{args.resolution}: {gflop:.0f} GFLOP per view (matrix products, "
              "torch.utils.flop_counter; counted on 16x16 rays)")
        out["view_paper_gflop"] = gflop
    # the op sequence does not depend on the number of rays: count with few (bf16 matmuls are slow on CPUs
    # without bf16 units)
    small, _ = synthetic_batch(args.objects, args.count_rays, args.resolution, depth_aware)
    proxy = make_step(model, cfg, small, device, args.step_shape, as_cuda=True)  # composed as on CUDA
    proxy()
    names = {id(m): n or "model" for n, m in model.named_modules()}
    with CountOps(breakdown=bool(args.breakdown), names=names) as counter:
        proxy()
    if args.breakdown:
        counter.report(args.breakdown)
    print(f"counted: the step composed as on CUDA (bf16 autocast, fused Adam; the legacy loop: foreach Adam), "
          f"{args.objects} objects x {args.count_rays} rays")
    print(f"of which views and allocations (no kernel on a GPU): {counter.no_kernel}")
    print(f"aten ops per training step: {counter.count}")
    out.update(aten_ops_per_step=counter.count, aten_ops_without_kernel=counter.no_kernel,
               count_rays=args.count_rays)


if __name__ == "__main__":
    main()
