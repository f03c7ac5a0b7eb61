"""Speed of the (depth-aware) pixelNeRF network on this machine: prints figures, asserts nothing.

Cases (each runs in a fresh subprocess so its peak RSS, ``ru_maxrss``, is its own):

- ``peak``   fp32 / bf16 matmul throughput of one big ``torch.mm`` (the reference for "fraction of peak").
- ``mlp``    the NeRF MLP alone (``ResidualField``) on N points: forward, forward+backward, bf16-autocast forward;
             FLOP/s and fraction of the fp32 peak.
- ``field``  one coarse field call (projection + feature sampling + MLP), ``lin_z`` per point vs on the map,
             training (fwd+bwd) and inference; points/s.
- ``encoder`` the encoder on B source views, forward and forward+backward.
- ``iter``   a full training iteration (encode, ``render_rays`` coarse+fine, L2 loss, backward, Adam step).
- ``view``   a novel view rendered with ``render_image`` (no grad), fp32 and bf16 autocast.

Settings (``--setting``): ``paper`` (ResNet34, d_hidden 512, 64/16/16 samples, 128x128, 4 objects x 128 rays),
``ref-small`` (the same with d_hidden 128 and 32/16/8 samples: the reference's reduced run), and CPU candidates
``cpu-64-d128`` / ``cpu-64-d256`` (64x64 images, 32/16/8 samples), ``cpu-64-r18`` (ResNet18, d_hidden 128).

Each case runs with glibc malloc tuned as the CLI runs (``depthnerf.cpu_runtime.keep_freed_memory``);
``--glibc-malloc-default`` measures without it.

Usage: ``python benchmarks/bench_model.py --setting paper --cases peak mlp field iter view``.
"""

from __future__ import annotations

import argparse
import math
import multiprocessing as mp
import os
import resource
import statistics
import time
from dataclasses import dataclass

import torch

from depthnerf.cpu_runtime import keep_freed_memory
from depthnerf.data.cameras import Intrinsics, look_at
from depthnerf.model import EncoderConfig, FieldConfig, PixelNeRF, PixelNeRFConfig, SourceViews
from depthnerf.model.field import ResidualField
from depthnerf.render import (
    RayBundle,
    RenderConfig,
    SamplerConfig,
    rays_from_camera,
    render_image,
    render_rays,
)


@dataclass(frozen=True)
class Setting:
    """One benchmarked configuration."""

    resolution: int
    """Image size (square)."""
    backbone: str
    """torchvision trunk."""
    d_hidden: int
    """MLP width."""
    samples: tuple[int, int, int]
    """(coarse, importance, gaussian) samples per ray; the fine pass evaluates all three."""
    objects: int = 4
    """Objects per training batch."""
    rays: int = 128
    """Rays per object per training iteration."""
    depth_aware: bool = False
    """Depth-aware encoder."""

    def model_config(self, lin_z_on_map: bool = True, chunk: int = FieldConfig.chunk_points) -> PixelNeRFConfig:
        fc = FieldConfig(d_hidden=self.d_hidden, lin_z_on_map=lin_z_on_map, chunk_points=chunk)
        return PixelNeRFConfig(encoder=EncoderConfig(backbone=self.backbone),
                               coarse=fc, fine=fc)

    def render_config(self) -> RenderConfig:
        c, i, g = self.samples
        return RenderConfig(sampler=SamplerConfig(n_coarse=c, n_importance=i, n_gaussian=g))


SETTINGS = {
    "paper": Setting(128, "resnet34", 512, (64, 16, 16)),
    "paper-depth": Setting(128, "resnet34", 512, (64, 16, 16), depth_aware=True),
    "ref-small": Setting(128, "resnet34", 128, (32, 16, 8)),
    "cpu-64-d128": Setting(64, "resnet34", 128, (32, 16, 8)),
    "cpu-64-d256": Setting(64, "resnet34", 256, (32, 16, 8)),
    "cpu-64-r18": Setting(64, "resnet18", 128, (32, 16, 8)),
    "cpu-64-d128-depth": Setting(64, "resnet34", 128, (32, 16, 8), depth_aware=True),
    "cpu-64-d64": Setting(64, "resnet34", 64, (32, 16, 8)),
    "cpu-64-d128-s24": Setting(64, "resnet34", 128, (24, 8, 8)),
    "cpu-64-d128-r64": Setting(64, "resnet34", 128, (32, 16, 8), rays=64),
}


def best_time(fn, repeat: int, clock: str, warmup: int = 1) -> float:
    """Minimum time of ``fn()`` over ``repeat`` runs after ``warmup`` runs (robust to a shared machine).

    ``clock="wall"``: elapsed time. ``clock="cpu"``: this process's CPU time, which on a machine shared with
    other jobs approximates the elapsed time the run would take alone (meaningful with ``--threads 1``; with
    more threads it also counts OpenMP spin-waiting).
    """
    now = time.perf_counter if clock == "wall" else time.process_time
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        t0 = now()
        fn()
        times.append(now() - t0)
    return min(times)


def mlp_flops(d_in: int, d: int, n_blocks: int, n_lin_z: int, latent: int, per_point_lin_z: bool) -> int:
    """Forward FLOPs (2 per multiply-add) of the MLP for one point and one source view."""
    return 2 * (d_in * d + n_blocks * 2 * d * d + d * 4 + (n_lin_z * latent * d if per_point_lin_z else 0))


def scene(setting: Setting, b: int, seed: int = 0) -> tuple[SourceViews, torch.Tensor, Intrinsics]:
    """Random images on a camera sphere (SRN cars geometry), plus target poses."""
    gen = torch.Generator().manual_seed(seed)
    res = setting.resolution
    intr = Intrinsics(focal=131.25 * res / 128, cx=(res - 1) / 2, cy=(res - 1) / 2, height=res, width=res)
    az = torch.rand(b, 2, generator=gen) * 2 * math.pi
    eye = torch.stack([1.3 * torch.cos(az) * 0.9, 1.3 * torch.sin(az) * 0.9, torch.full_like(az, 0.57)], -1)
    poses = look_at(eye)
    src = SourceViews(images=torch.rand(b, 1, 3, res, res, generator=gen), poses=poses[:, :1],
                      focal=torch.full((b,), intr.focal), principal=torch.full((b, 2), intr.cx),
                      disparity=torch.randn(b, 1, 1, res, res, generator=gen) if setting.depth_aware else None)
    return src, poses[:, 1], intr


def case_peak(args) -> None:
    n = 4096
    for dtype in (torch.float32, torch.bfloat16):
        a, b = torch.randn(n, n, dtype=dtype), torch.randn(n, n, dtype=dtype)
        t = best_time(lambda a=a, b=b: torch.mm(a, b), args.repeat, args.clock)
        print(f"peak  torch.mm {n}^3 {str(dtype)[6:]:8s}: {2 * n ** 3 / t / 1e9:7.1f} GFLOP/s")


def measured_peak(clock: str) -> float:
    a, b = torch.randn(4096, 4096), torch.randn(4096, 4096)
    return 2 * 4096 ** 3 / best_time(lambda: torch.mm(a, b), 3, clock) / 1e9


def case_mlp(args, setting: Setting) -> None:
    n = args.points
    cfg = FieldConfig(d_hidden=setting.d_hidden)
    mlp = ResidualField(cfg, 512)
    x = torch.randn(1, 1, n, cfg.d_in)
    z = torch.randn(1, 1, n, 3 * cfg.d_hidden, requires_grad=True)
    flops = n * mlp_flops(cfg.d_in, cfg.d_hidden, cfg.n_blocks, 3, 512, per_point_lin_z=False)
    peak = measured_peak(args.clock)

    def fwd_bwd():
        mlp(x, z, projected=True).sum().backward()

    with torch.no_grad():
        t_f = best_time(lambda: mlp(x, z, projected=True), args.repeat, args.clock)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            t_bf = best_time(lambda: mlp(x, z, projected=True), args.repeat, args.clock)
    t_fb = best_time(fwd_bwd, args.repeat, args.clock)
    print(f"mlp   d={cfg.d_hidden} N={n}: fp32 peak now {peak:.0f} GFLOP/s")
    for name, t, fl in (("fwd fp32", t_f, flops), ("fwd+bwd fp32", t_fb, 3 * flops), ("fwd bf16", t_bf, flops)):
        print(f"mlp   {name:13s}: {t * 1e3:8.1f} ms  {fl / t / 1e9:6.1f} GFLOP/s  = {fl / t / 1e9 / peak:5.0%} of fp32 "
              f"peak  ({n / t:,.0f} points/s)")


def case_field(args, setting: Setting) -> None:
    b = setting.objects
    src, _, _ = scene(setting, b)
    n_pts = args.points // b
    gen = torch.Generator().manual_seed(1)
    pts = (torch.rand(b, n_pts, 1, 3, generator=gen) - 0.5) * 0.8
    dirs = torch.nn.functional.normalize(torch.randn(b, n_pts, 3, generator=gen), dim=-1)
    cfg = setting.model_config()
    for on_map in (False, True):
        torch.manual_seed(0)
        model = PixelNeRF(setting.model_config(lin_z_on_map=on_map), depth_aware=setting.depth_aware)

        def train_step(model=model):
            enc = model.encode(src)
            rgb, sigma = model.field(enc, "coarse")(pts, dirs)
            (rgb.sum() + sigma.sum()).backward()

        with torch.no_grad():
            enc = model.encode(src)

        def infer(model=model, enc=enc):
            with torch.no_grad():
                model.field(enc, "coarse")(pts, dirs)
        t_tr, t_in = best_time(train_step, args.repeat, args.clock), best_time(infer, args.repeat, args.clock)
        latent = cfg.encoder.latent_size(setting.depth_aware)
        flops = b * n_pts * mlp_flops(cfg.coarse.d_in, setting.d_hidden, 5, 3, latent, not on_map)
        print(f"field lin_z_on_map={on_map!s:5s}: train (encode+field fwd+bwd) {t_tr:6.2f} s "
              f"({b * n_pts / t_tr:8,.0f} pts/s); inference {t_in:6.2f} s ({b * n_pts / t_in:9,.0f} pts/s, "
              f"MLP-equivalent {flops / t_in / 1e9:5.1f} GFLOP/s)")


def case_encoder(args, setting: Setting) -> None:
    src, _, _ = scene(setting, setting.objects)
    model = PixelNeRF(setting.model_config(), depth_aware=setting.depth_aware)

    def fwd_bwd():
        model.encode(src).features.sum().backward()

    with torch.no_grad():
        t_f = best_time(lambda: model.encode(src), args.repeat, args.clock)
    t_fb = best_time(fwd_bwd, args.repeat, args.clock)
    print(f"enc   {setting.backbone} {setting.objects}x{setting.resolution}^2: fwd {t_f * 1e3:.0f} ms, "
          f"fwd+bwd {t_fb * 1e3:.0f} ms")


def case_iter(args, setting: Setting) -> None:
    torch.manual_seed(0)
    b = setting.objects
    src, target_poses, intr = scene(setting, b)
    model = PixelNeRF(setting.model_config(lin_z_on_map=not args.lin_z_per_point),
                      depth_aware=setting.depth_aware).train()
    rcfg = setting.render_config()
    opt = torch.optim.Adam(model.parameters(), lr=1e-4)
    gen = torch.Generator().manual_seed(0)
    all_rays = rays_from_camera(target_poses, intr, 0.8, 1.8)
    target = torch.rand(b, all_rays.num_rays, 3, generator=gen)

    def step():
        idx = torch.randint(0, all_rays.num_rays, (b, setting.rays), generator=gen)
        pick = [torch.gather(t, 1, idx[..., None].expand(-1, -1, 3)) for t in (all_rays.origins, all_rays.directions)]
        rays = RayBundle(pick[0], pick[1], torch.full((b, setting.rays), 0.8), torch.full((b, setting.rays), 1.8))
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=args.train_bf16):
            enc = model.encode(src)
            out = render_rays(model.field(enc, "coarse"), model.field(enc, "fine"), rays, rcfg, train=True,
                              generator=gen)
        gt = torch.gather(target, 1, idx[..., None].expand(-1, -1, 3))
        loss = (out.coarse.rgb - gt).square().mean() + (out.fine.rgb - gt).square().mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    step()
    now = time.perf_counter if args.clock == "wall" else time.process_time
    times = []
    for _ in range(args.repeat):
        t0 = now()
        step()
        times.append(now() - t0)
    c, i, g = setting.samples
    pts = b * setting.rays * (2 * c + i + g)
    print(f"iter  {'bf16 autocast' if args.train_bf16 else 'fp32'} {b}x{setting.rays} rays, {c}+{c + i + g} samples: best {min(times):.3f} s, median "
          f"{statistics.median(times):.3f} s per iteration -> {b * setting.rays / min(times):,.0f} rays/s, "
          f"{1 / min(times):.2f} it/s ({pts:,} field points/iter)")


def case_view(args, setting: Setting) -> None:
    torch.manual_seed(0)
    src, target_poses, intr_full = scene(setting, 1)
    model = PixelNeRF(setting.model_config(lin_z_on_map=not args.lin_z_per_point, chunk=args.chunk),
                      depth_aware=setting.depth_aware).eval()
    rcfg = setting.render_config()
    with torch.no_grad():
        enc = model.encode(src)
    for res in args.view_sizes:
        intr = intr_full.resized(res, res)
        rays = rays_from_camera(target_poses, intr, 0.8, 1.8)
        for label, ctx in (("fp32", None), ("bf16", torch.bfloat16)):
            def render(rays=rays, ctx=ctx):
                with torch.autocast("cpu", dtype=ctx, enabled=ctx is not None):
                    return render_image(model.field(enc, "coarse"), model.field(enc, "fine"), rays, rcfg,
                                        chunk=args.render_chunk)
            t = best_time(render, max(1, args.repeat // 2), args.clock, warmup=0)
            print(f"view  {res}x{res} {label} lin_z {'per point' if args.lin_z_per_point else 'on map'}: {t * 1e3:10,.0f} ms per view ({res * res / t:,.0f} rays/s)")


CASES = {"peak": case_peak, "mlp": case_mlp, "field": case_field, "encoder": case_encoder, "iter": case_iter,
         "view": case_view}


def _run_case(name: str, args, setting: Setting) -> None:
    tuned = keep_freed_memory()  # False with --glibc-malloc-default (DEPTHNERF_MALLOC_TUNING=0, set by main)
    torch.set_num_threads(args.threads)
    if name == "peak":
        case_peak(args)
    else:
        CASES[name](args, setting)
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"      [{name}: peak RSS {rss:,.0f} MiB, {torch.get_num_threads()} threads, "
          f"load avg {os.getloadavg()[0]:.1f}, malloc {'tuned' if tuned else 'default'}]", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--setting", choices=sorted(SETTINGS), default="paper")
    parser.add_argument("--cases", nargs="+", choices=sorted(CASES), default=["peak", "mlp", "field", "iter"])
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--clock", choices=["wall", "cpu"], default="wall",
                        help="wall time, or process CPU time (use with --threads 1 on a shared machine)")
    parser.add_argument("--train-bf16", action="store_true", help="iter case: forward under bf16 autocast")
    parser.add_argument("--lin-z-per-point", action="store_true", help="iter/view: lin_z per point (pixelNeRF)")
    parser.add_argument("--points", type=int, default=16384, help="points for the mlp/field cases")
    parser.add_argument("--view-sizes", type=int, nargs="+", default=[64, 128])
    parser.add_argument("--render-chunk", type=int, default=4096, help="rays per render_image chunk")
    parser.add_argument("--glibc-malloc-default", action="store_true",
                        help="leave glibc malloc at its defaults (see depthnerf.cpu_runtime) to measure the difference")
    parser.add_argument("--chunk", type=int, default=FieldConfig.chunk_points, help="FieldConfig.chunk_points (views)")
    args = parser.parse_args()
    setting = SETTINGS[args.setting]
    if args.glibc_malloc_default:  # the spawned cases import depthnerf, which would tune malloc
        os.environ["DEPTHNERF_MALLOC_TUNING"] = "0"
    print(f"setting {args.setting}: {setting}; clock {args.clock}, {args.threads} threads")
    ctx = mp.get_context("spawn")
    failed = []
    for name in args.cases:
        proc = ctx.Process(target=_run_case, args=(name, args, setting))
        proc.start()
        proc.join()
        if proc.exitcode != 0:  # a case's traceback is on stderr; the run still goes on to the other cases
            failed.append(f"{name} (exit {proc.exitcode})")
    if failed:
        raise SystemExit(f"error: cases failed: {', '.join(failed)}")


if __name__ == "__main__":
    main()
