"""Benchmark: depth-guided sampling vs the paper's sampling (64 coarse + 16 importance + 16 Gaussian, two nets).

Prints, per target view and on average: network evaluations per ray, wall time per view (guide building
included for the guided path; the one-off source alignment is reported separately, amortised over the views)
and PSNR of both renders against a reference, plus the PSNR between the two renders.

Modes
    analytic (default): a sphere scene (``render.analytic.SphereScene``) whose dense quadrature (4096 samples) is
        the reference. The field is optionally wrapped with a dummy MLP (``--mlp-width/--mlp-layers``, output
        multiplied by 0) so wall time scales with network evaluations as with a real pixelNeRF. The source prior
        is a relative disparity ``a / z + b`` with a smooth multiplicative error (``--prior-error``), normalised
        like the depth stage's priors, and aligned to metric depth against a cheap coarse render of the source.
    checkpoint (``--checkpoint SPEC --data ROOT``): a trained pixelNeRF on SRN-protocol objects, its own sampler
        against depth-guided sampling at several sample budgets, metrics against ground truth; see
        ``guided_checkpoint.py`` (beside this script) for exactly what is measured.

Usage: ``python benchmarks/bench_guided_sampling.py [--res 64 --views 4 --mlp-width 128 --mlp-layers 4]``, or
``python benchmarks/bench_guided_sampling.py --checkpoint RUN --data ROOT [--category C --split test --objects N
--views-stride K --budgets 8,16,24,32 --json OUT]``

Wall times on a shared CPU are noisy; evaluations per ray are exact. A real pixelNeRF costs far more per sample
than the default dummy MLP (ResNet-FC 512 wide), so its speed-up approaches the evaluation ratio.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass

import torch
from guided_checkpoint import run_checkpoint, source_depth, timed

from depthnerf.cpu_runtime import keep_freed_memory
from depthnerf.data.cameras import Intrinsics, look_at
from depthnerf.depth.normalize import normalize_disparity
from depthnerf.errors import DepthnerfError
from depthnerf.render.analytic import Sphere, SphereScene
from depthnerf.render.config import GuidedConfig, RenderConfig, SamplerConfig
from depthnerf.render.depth_guide import build_depth_guide
from depthnerf.render.pipeline import FieldFn, render_image
from depthnerf.render.rays import rays_from_camera


@dataclass
class Subject:
    """What the benchmark renders: one object seen from a source view, and target views to render."""

    coarse: FieldFn
    """Coarse network (already conditioned on the source view)."""
    fine: FieldFn | None
    """Fine network."""
    intr: Intrinsics
    """Intrinsics of source and target views."""
    near: float
    """Near ray distance."""
    far: float
    """Far ray distance."""
    source_c2w: torch.Tensor
    """[1 4 4] source pose."""
    source_prior: torch.Tensor
    """[1 H W] relative disparity prior of the source view."""
    source_mask: torch.Tensor
    """[1 H W] foreground mask of the source view."""
    target_c2w: torch.Tensor
    """[N 4 4] target poses."""
    reference: Callable[[int], torch.Tensor]
    """Reference image [H*W 3] of target view ``i`` (ground truth, or a dense render for analytic scenes)."""


class _Counted:
    """A field wrapper counting evaluated points, with an optional dummy MLP to emulate network cost."""

    def __init__(self, field: FieldFn, width: int, layers: int):
        self.field, self.points = field, 0
        mods = []
        for _ in range(layers):
            mods += [torch.nn.Linear(width, width), torch.nn.ReLU()]
        self.mlp = torch.nn.Sequential(*mods) if layers > 0 else None
        self.width = width

    def __call__(self, pts: torch.Tensor, dirs: torch.Tensor):
        self.points += pts.shape[:-1].numel()
        rgb, sigma = self.field(pts, dirs)
        if self.mlp is not None:
            x = pts.repeat_interleave(math.ceil(self.width / 3), dim=-1)[..., : self.width]
            sigma = sigma + 0.0 * self.mlp(x)[..., 0]
        return rgb, sigma


def spiral_poses(n: int, radius: float) -> torch.Tensor:
    """``n`` cameras on an upward spiral around the origin (like the SRN test trajectories)."""
    eyes = []
    for k in range(n):
        el = math.radians(10 + 60 * (k + 0.5) / n)
        az = math.radians(25 + 360 * 1.5 * k / max(n, 1))
        eyes.append([radius * math.cos(el) * math.cos(az), radius * math.cos(el) * math.sin(az),
                     radius * math.sin(el)])
    return look_at(torch.tensor(eyes))


def analytic_subject(args: argparse.Namespace) -> Subject:
    scene = SphereScene((Sphere((0.0, 0.0, 0.0), 0.33), Sphere((0.22, 0.28, 0.12), 0.14),
                         Sphere((-0.3, -0.1, -0.15), 0.1)), beta=args.beta)
    intr = Intrinsics(131.25, 63.5, 63.5, 128, 128).resized(args.res, args.res)
    near, far = 0.8, 1.8
    src = look_at(torch.tensor([[1.3 * math.cos(0.35), 0.0, 1.3 * math.sin(0.35)]]))
    z, mask = scene.depth_map(src, intr, near, far)
    u = torch.linspace(-1, 1, args.res)
    distortion = 1 + args.prior_error * torch.sin(3 * u[:, None] + 1) * torch.cos(2 * u[None, :])
    disp = torch.where(mask, 0.37 / (z * distortion).clamp_min(1e-3) + 2.0, torch.zeros_like(z))
    targets = spiral_poses(args.views, 1.3)
    dense = RenderConfig(sampler=SamplerConfig(n_coarse=4096))

    def reference(i: int) -> torch.Tensor:
        rays = rays_from_camera(targets[i:i + 1], intr, near, far)
        return render_image(scene, None, rays, dense, chunk=1024).coarse.rgb[0]

    field = _Counted(scene, args.mlp_width, args.mlp_layers)
    return Subject(field, field, intr, near, far, src, normalize_disparity(disp, mask), mask, targets, reference)


def align_source(s: Subject, samples: int) -> tuple[torch.Tensor, float]:
    """Metric source z-depth: the prior aligned against a coarse-only render of the source view."""
    t0 = time.perf_counter()
    z = source_depth(s.coarse, s.source_c2w, s.intr, s.near, s.far, s.source_prior, s.source_mask, RenderConfig(),
                     GuidedConfig(align_samples=samples, align_min_opacity=0.5))
    return z, time.perf_counter() - t0


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return -10 * math.log10(max(((a.clamp(0, 1) - b) ** 2).mean().item(), 1e-20))


def run(s: Subject, args: argparse.Namespace) -> None:
    counter = s.coarse if isinstance(s.coarse, _Counted) else None
    aligned, t_align = align_source(s, args.align_samples)
    guide_cfg = GuidedConfig(spread=args.spread)
    paper, guided = RenderConfig(), RenderConfig(guided=GuidedConfig(enabled=True))
    rows = []
    print(f"source alignment: {t_align:.3f} s once ({t_align / len(s.target_c2w):.3f} s per view amortised over "
          f"{len(s.target_c2w)} views)")
    print("| view | evals/ray paper | evals/ray guided | s/view paper | s/view guided | speed-up | "
          "PSNR paper | PSNR guided | PSNR guided vs paper | occupied rays |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for i in range(len(s.target_c2w)):
        rays = rays_from_camera(s.target_c2w[i:i + 1], s.intr, s.near, s.far)
        n_rays = rays.near.numel()
        ref = s.reference(i)

        def render_paper(rays=rays):
            return render_image(s.coarse, s.fine, rays, paper, chunk=args.chunk).final.rgb[0]

        def render_guided(rays=rays):
            guide = build_depth_guide(s.source_c2w, s.intr, aligned, s.source_mask, rays, guide_cfg)
            return render_image(s.coarse, s.fine, rays, guided, chunk=args.chunk, guide=guide).final.rgb[0], guide

        p0 = counter.points if counter else 0
        full, t_full = timed(render_paper, args.repeats)
        p1 = counter.points if counter else 0
        (fast, guide), t_fast = timed(render_guided, args.repeats)
        p2 = counter.points if counter else 0
        row = ((p1 - p0) / n_rays / args.repeats, (p2 - p1) / n_rays / args.repeats, t_full, t_fast, t_full / t_fast, psnr(full, ref),
               psnr(fast, ref), psnr(fast, full), guide.occupied.float().mean().item())
        rows.append(row)
        print(f"| {i} | {row[0]:.1f} | {row[1]:.1f} | {row[2]:.3f} | {row[3]:.3f} | {row[4]:.2f}x | {row[5]:.2f} | "
              f"{row[6]:.2f} | {row[7]:.2f} | {row[8]:.2f} |")
    mean = [sum(r[k] for r in rows) / len(rows) for k in range(len(rows[0]))]
    total_full, total_fast = sum(r[2] for r in rows), sum(r[3] for r in rows) + t_align
    print(f"| mean | {mean[0]:.1f} | {mean[1]:.1f} | {mean[2]:.3f} | {mean[3]:.3f} | {mean[4]:.2f}x | "
          f"{mean[5]:.2f} | {mean[6]:.2f} | {mean[7]:.2f} | {mean[8]:.2f} |")
    print(f"total wall time incl. alignment: paper {total_full:.2f} s, guided {total_fast:.2f} s "
          f"({total_full / total_fast:.2f}x); mean PSNR change guided - paper: {mean[6] - mean[5]:+.3f} dB")
    if args.model_psnr > 0:
        # ||guided - gt|| <= ||paper - gt|| + ||guided - paper|| (RMS triangle inequality): a rigorous bound
        worst = max(20 * math.log10(1 + 10 ** ((args.model_psnr - r[7]) / 20)) for r in rows)
        typical = max(10 * math.log10(1 + 10 ** ((args.model_psnr - r[7]) / 10)) for r in rows)
        print(f"for a model whose paper-sampling renders are {args.model_psnr:.1f} dB from ground truth, the "
              f"guided renders lose at most {worst:.3f} dB (worst view, triangle inequality on RMS error), "
              f"{typical:.4f} dB if the two errors are uncorrelated")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", help="checkpoint mode: a trained checkpoint (any spec depthnerf eval accepts)")
    p.add_argument("--data", help="checkpoint mode: dataset root (SRN layout, with the checkpoint's prior cache)")
    p.add_argument("--category", help="checkpoint mode: category (default: the checkpoint's)")
    p.add_argument("--split", default="test", help="checkpoint mode: split")
    p.add_argument("--objects", type=int, default=2, help="checkpoint mode: first N objects of the split")
    p.add_argument("--views-stride", type=int, default=25, help="checkpoint mode: every K-th target view")
    p.add_argument("--budgets", default="8,16,24,32", help="checkpoint mode: guided samples per occupied ray")
    p.add_argument("--reference-samples", metavar="C,I,G",
                   help="checkpoint mode: reference sampler counts (coarse, importance, Gaussian), e.g. the paper's "
                        "64,16,16 (default: the checkpoint's own sampler)")
    p.add_argument("--plain-samplers", metavar="'C,I,G ...'",
                   help="checkpoint mode: extra unguided rows with these sampler counts (space-separated)")
    p.add_argument("--align-min-opacity", type=float, default=0.5,
                   help="checkpoint mode: source pixels at least this opaque in the alignment render anchor the prior")
    p.add_argument("--json", help="checkpoint mode: write the table as JSON here")
    p.add_argument("--res", type=int, default=64, help="image side in pixels (analytic mode)")
    p.add_argument("--views", type=int, default=4, help="number of target views (analytic mode)")
    p.add_argument("--beta", type=float, default=0.005, help="sphere surface softness (analytic mode)")
    p.add_argument("--prior-error", type=float, default=0.03, help="relative depth error of the prior")
    p.add_argument("--mlp-width", type=int, default=128, help="dummy MLP width emulating network cost")
    p.add_argument("--mlp-layers", type=int, default=4, help="dummy MLP layers (0: analytic field only)")
    p.add_argument("--align-samples", type=int, default=32, help="coarse samples of the source alignment render")
    p.add_argument("--spread", type=float, default=GuidedConfig.spread, help="guide window half-width")
    p.add_argument("--chunk", type=int, default=4096, help="rays per chunk")
    p.add_argument("--repeats", type=int, default=2, help="time each render this many times, keep the fastest")
    p.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    p.add_argument("--model-psnr", type=float, default=23.0,
                   help="analytic mode: PSNR of a typical model vs ground truth, for the worst-case loss bound")
    args = p.parse_args(argv)
    keep_freed_memory()  # as the depthnerf CLI does (depthnerf.cpu_runtime)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    if args.checkpoint:
        if not args.data:
            p.error("--checkpoint needs --data")
        try:
            run_checkpoint(args)
        except DepthnerfError as err:
            print(f"error: {err}", file=sys.stderr)
            return 2
        return 0
    if args.json:
        p.error("--json is for checkpoint mode (--checkpoint)")
    run(analytic_subject(args), args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
