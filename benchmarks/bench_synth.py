"""Throughput of ``depthnerf synth`` (target: >= 60 train objects of 50 views per minute on 2 cores).

Prints (1) a per-stage breakdown of one in-process worker: mesh build, render and file writing per view, with
wall-clock and CPU time (CPU time is what a free core would need: the 2-core estimate is 2 * 60 / CPU seconds
per object, useful when other jobs share the machine), and (2) end-to-end objects/min and ms/view of the real
generator (process pool, files on disk) for train objects, wall clock including pool start-up. The machine's
load average is printed too, since other processes slow the wall-clock figures.

    python benchmarks/bench_synth.py --category cars --objects 12 --workers 2
    python benchmarks/bench_synth.py --raycaster torch --objects 16 --workers 8   # the ray caster without embreex
                                                                                 # (CUDA when there is one)
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from depthnerf.data import srn_format
from depthnerf.data.synth.generate import SynthConfig, category_spec, generate, object_poses, object_rngs
from depthnerf.data.synth.raycast import PixelRays, Raycaster, SynthRenderConfig, render_view


def breakdown(category: str, objects: int, views: int, resolution: int, raycaster: str) -> None:
    torch.set_num_threads(1)
    from depthnerf.data.synth.cars import build_car, sample_car
    from depthnerf.data.synth.chairs import build_chair, sample_chair

    cfg = SynthConfig(category=category, out=Path("."), resolution=resolution)
    rays = PixelRays(cfg.intrinsics())
    t_build = t_render = t_write = 0.0
    edge = []
    cpu0, wall0 = time.process_time(), time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(objects):
            shape_rng, view_rng = object_rngs(123, category, "train", k)
            t0 = time.perf_counter()
            mesh = build_car(sample_car(shape_rng)) if category == "cars" else build_chair(sample_chair(shape_rng))
            caster = Raycaster(mesh, raycaster)
            t_build += time.perf_counter() - t0
            poses = object_poses("train", views, category_spec(category), view_rng)
            for v, c2w in enumerate(poses):
                t0 = time.perf_counter()
                view = render_view(caster, c2w, rays, SynthRenderConfig())
                t1 = time.perf_counter()
                base = Path(tmp) / f"{k}_{v}"
                srn_format.write_rgb(base.with_suffix(".png"), view.rgb)
                srn_format.write_pose(base.with_suffix(".txt"), c2w)
                srn_format.write_depth(base.with_suffix(".npz"), view.depth)
                srn_format.write_mask(base.with_name(base.name + "_m.png"), view.mask)
                t_write += time.perf_counter() - t1
                t_render += t1 - t0
                edge.append(view.mask.mean())
    cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
    n = objects * views
    print(f"[breakdown, 1 process, {caster.engine}] {category} {resolution}px: build+BVH {1000 * t_build / objects:.1f} ms/object, "
          f"render {1000 * t_render / n:.2f} ms/view, write {1000 * t_write / n:.2f} ms/view (wall); "
          f"total {1000 * wall / n:.2f} ms/view wall, {1000 * cpu / n:.2f} ms/view CPU -> "
          f"{2 * 60 * objects / cpu:.0f} objects/min on 2 free cores; mean mask coverage {np.mean(edge):.3f}")


def end_to_end(category: str, objects: int, workers: int, resolution: int, raycaster: str) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        cfg = SynthConfig(category=category, out=Path(tmp), train_objects=objects, val_objects=0, test_objects=0,
                          resolution=resolution, workers=workers, progress=False, raycaster=raycaster)
        t0 = time.perf_counter()
        generate(cfg)
        dt = time.perf_counter() - t0
    views = objects * cfg.views_train
    print(f"[end to end, {workers} workers, {raycaster}] {category}: {objects} train objects x {cfg.views_train} views in "
          f"{dt:.1f} s -> {60 * objects / dt:.1f} objects/min, {1000 * dt / views:.2f} ms/view (wall, incl. "
          f"pool start-up)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--category", choices=["cars", "chairs", "both"], default="both")
    parser.add_argument("--objects", type=int, default=12, help="train objects for the end-to-end run")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--breakdown-objects", type=int, default=3)
    parser.add_argument("--raycaster", choices=["auto", "embree", "torch"], default="auto",
                        help="first-hit engine (depthnerf synth --raycaster)")
    args = parser.parse_args()
    print(f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())} on {os.cpu_count()} cores")
    for category in (["cars", "chairs"] if args.category == "both" else [args.category]):
        breakdown(category, args.breakdown_objects, 50, args.resolution, args.raycaster)
        end_to_end(category, args.objects, args.workers, args.resolution, args.raycaster)


if __name__ == "__main__":
    main()
