"""Field points per MLP call on the CPU: wall time of one photo's reconstruction for several point chunks (prints
figures, asserts nothing).

The inference policy's ``CPU_POINT_CHUNK`` (:mod:`depthnerf.render.precision`) comes from this: small chunks pay
a thread synchronisation and Python overhead per call that more threads make worse. Set the threads the way you
run (``OMP_NUM_THREADS``); rounds interleave the chunks so that a change of load hits them alike.

    OMP_NUM_THREADS=2 python benchmarks/bench_point_chunk.py --chunks 4096 8192 16384 32768 --rounds 2
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time

import torch

from depthnerf import Reconstructor
from depthnerf.app.logic import EXAMPLES_DIR
from depthnerf.reconstruct.reconstructor import ReconstructConfig
from depthnerf.render.precision import inference_policy


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", default="cpu-cars-sym-pp")
    p.add_argument("--image", default=str(EXAMPLES_DIR / "car_rgba.png"))
    p.add_argument("--chunks", type=int, nargs="+", default=[4096, 8192, 16384, 32768])
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--views", type=int, default=8)
    p.add_argument("--mesh-resolution", type=int, default=64)
    args = p.parse_args()
    cfg = ReconstructConfig(views=args.views, mesh_resolution=args.mesh_resolution)
    cpu = inference_policy("cpu")
    recs = {c: Reconstructor.from_pretrained(args.checkpoint, policy=dataclasses.replace(cpu, point_chunk=c))
            for c in args.chunks}
    times: dict[int, list[float]] = {c: [] for c in args.chunks}
    for rec in recs.values():
        rec.reconstruct(args.image, config=cfg)  # warm-up (allocator, first-call costs)
    for _ in range(args.rounds):
        for c, rec in recs.items():
            t = time.perf_counter()
            rec.reconstruct(args.image, config=cfg)
            times[c].append(time.perf_counter() - t)
    print(f"{args.checkpoint}, {args.views} views + {args.mesh_resolution}-sample mesh, "
          f"{torch.get_num_threads()} threads, {args.rounds} rounds")
    for c, t in times.items():
        print(f"point chunk {c:6d}: {min(t):.2f} s best, {statistics.median(t):.2f} s median")


if __name__ == "__main__":
    main()
