"""``depthnerf demo [--out DIR]``: one-command demo, no data and no network needed.

Synthesises one unseen car and one unseen chair (``depthnerf synth`` test object 0 of ``--seed``, default
:data:`depthnerf.demo.DEMO_SEED`), reconstructs each from its view 64 with the shipped depth-aware
checkpoints (``--cars-checkpoint`` / ``--chairs-checkpoint``: any checkpoint name or path), scores every
``--views-stride``-th true view by the SRN protocol with the metric code of ``depthnerf eval`` and writes input,
depth prior, novel views vs truth, a turntable GIF, a mesh and ``OUT/demo.json`` (layout in
:mod:`depthnerf.demo`). Prints a summary table, where the files are and its own wall time.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path


def add_arguments(p: argparse.ArgumentParser) -> None:
    from depthnerf.demo import CATEGORIES, DEFAULT_CHECKPOINTS, DEMO_SEED

    p.add_argument("--out", type=Path, default=Path("demo_out"), help="output folder (default demo_out)")
    p.add_argument("--seed", type=int, default=DEMO_SEED,
                   help=f"synthesis seed of the demo objects (default {DEMO_SEED}; training data uses seed 0)")
    p.add_argument("--views-stride", type=int, default=25,
                   help="score every K-th of the 250 target views (default 25: 10 views)")
    for cat in CATEGORIES:
        p.add_argument(f"--{cat}-checkpoint", default=DEFAULT_CHECKPOINTS[cat],
                       help=f"{cat} checkpoint: shipped name, weights file or run folder (default "
                            f"{DEFAULT_CHECKPOINTS[cat]})")
    p.add_argument("--categories", nargs="+", choices=CATEGORIES, default=list(CATEGORIES),
                   help="run only these categories (default: cars chairs)")
    p.add_argument("--turntable-views", type=int, default=16, help="turntable frames (default 16)")
    p.add_argument("--mesh-resolution", type=int, default=None, help="marching-cubes grid samples (default 96)")
    p.add_argument("--no-mesh", action="store_true", help="skip the mesh")
    p.add_argument("--device", default="auto", help="auto (CUDA if available), cpu, cuda or cuda:N")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")


def process_seconds() -> float | None:
    """Seconds since this process started (Linux ``/proc``; None elsewhere): includes Python and torch start-up."""
    try:
        start_ticks = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19])
        uptime = float(Path("/proc/uptime").read_text().split()[0])
        return uptime - start_ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


def check_checkpoint_flags(args: argparse.Namespace, categories: tuple[str, ...]) -> None:
    """One line when ``--<category>-checkpoint`` names another checkpoint than its default for a category that
    ``--categories`` leaves out (it would be ignored)."""
    from depthnerf.demo import CATEGORIES, DEFAULT_CHECKPOINTS
    from depthnerf.errors import DepthnerfError

    for cat in CATEGORIES:
        if cat not in categories and getattr(args, f"{cat}_checkpoint") != DEFAULT_CHECKPOINTS[cat]:
            raise DepthnerfError(f"--{cat}-checkpoint is given but --categories {' '.join(categories)} leaves "
                                 f"{cat} out: add {cat} to --categories or drop --{cat}-checkpoint")


def check_mesh_flags(args: argparse.Namespace) -> None:
    """One line when ``--mesh-resolution`` comes with ``--no-mesh`` (it would be ignored)."""
    from depthnerf.errors import DepthnerfError

    if args.no_mesh and args.mesh_resolution is not None:
        raise DepthnerfError("--mesh-resolution sets the mesh, which --no-mesh skips: pass one or the other")


def run(args: argparse.Namespace) -> int:
    from depthnerf.demo import DemoConfig, run_demo
    from depthnerf.distributed import pick_device

    t0 = time.perf_counter()
    cats = tuple(dict.fromkeys(args.categories))
    check_checkpoint_flags(args, cats)
    check_mesh_flags(args)
    mesh_resolution = {} if args.mesh_resolution is None else {"mesh_resolution": args.mesh_resolution}
    cfg = DemoConfig(out=args.out, seed=args.seed, categories=cats,
                     checkpoints={c: getattr(args, f"{c}_checkpoint") for c in cats},
                     views_stride=args.views_stride, turntable_views=args.turntable_views, mesh=not args.no_mesh,
                     progress=not args.no_progress, **mesh_resolution)
    demo = run_demo(cfg, pick_device(args.device))
    rows = [("category", "checkpoint", "prior", "object", "views", "PSNR", "SSIM", "seconds")]
    for cat, r in demo["categories"].items():
        rows.append((cat, r["checkpoint"], r["depth_prior"], r["object_id"],
                     f"{r['input_view']} -> {len(r['target_views'])}", f"{r['psnr']:.2f}", f"{r['ssim']:.3f}",
                     f"{r['seconds']['total_s']:.1f}"))
    widths = [max(len(row[k]) for row in rows) for k in range(len(rows[0]))]
    for row in rows:
        print("  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip())
    print(f"protocol: {demo['protocol']}")
    for cat, r in demo["categories"].items():
        for note in r["notes"][1:]:
            print(f"note ({cat}): {note}")
        mesh = "no mesh" if r["mesh_faces"] is None else f"mesh.ply with {r['mesh_faces']} faces"
        print(f"{cat}: {args.out / cat}/ (input.png, depth_prior.png, novel_views.png, turntable.gif, {mesh})")
    print(f"objects (SRN layout): {args.out / 'data'}; summary: {args.out / 'demo.json'}")
    since_start = process_seconds()
    print(f"demo wall time: {time.perf_counter() - t0:.1f} s"
          + (f" ({since_start:.1f} s since the command started, with Python and torch start-up)"
             if since_start is not None else ""))
    return 0
