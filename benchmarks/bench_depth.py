"""Depth-prior throughput on this machine: images/s per estimator backend, and cache reads/s.

    python benchmarks/bench_depth.py [--threads 2] [--batch-size 32] [--da-checkpoint DIR] [--cache-data DIR]

- ``bundled`` at 128 x 128 with the shipped weights (target: >= 50 images/s on 2 CPU cores);
- ``depth-anything-v2`` on a tiny randomly initialised checkpoint whose image processor works at 518 px like the
  real ones (measures the transformers preprocessing + model path, not real DA-V2 cost), and on a real local
  checkpoint directory when ``--da-checkpoint`` is given;
- ``--cache-data DIR``: ``PriorStore.load`` of 1 view per call from an existing bundled cache of that dataset
  (first cached ``<category>_<split>``; what a training data loader does per sample).

Prints one line per measurement (median and best of ``--repeats`` timed calls after a warm-up call); numbers
depend on what else runs on the machine.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import torch


def images_per_second(estimator, batch: torch.Tensor, repeats: int) -> str:
    """Median and best images/s over ``repeats`` timed calls (the machine is shared, so both are shown)."""
    estimator.predict(batch)  # warm-up (first call of a shape sets up kernels)
    rates = []
    for _ in range(repeats):
        start = time.perf_counter()
        estimator.predict(batch)
        rates.append(batch.shape[0] / (time.perf_counter() - start))
    return f"median {statistics.median(rates):8.1f}  best {max(rates):8.1f} images/s"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    parser.add_argument("--batch-size", type=int, default=32)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--da-checkpoint", default=None, help="local Depth Anything V2 checkpoint directory")
    parser.add_argument("--da-resolution", type=int, default=128, help="image size fed to DA-V2 (default 128)")
    parser.add_argument("--cache-data", type=Path, default=None, help="dataset with a bundled prior cache")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    from depthnerf.depth.depth_anything import make_tiny_checkpoint
    from depthnerf.depth.estimators import make_estimator

    gen = torch.Generator().manual_seed(0)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads")
    batch = torch.rand(args.batch_size, 3, 128, 128, generator=gen)
    bundled = make_estimator("bundled")
    rate = images_per_second(bundled, batch, args.repeats)
    print(f"bundled            128x128  batch {args.batch_size:3d}: {rate}  (target >= 50)")

    da_batch = torch.rand(min(args.batch_size, 8), 3, args.da_resolution, args.da_resolution, generator=gen)
    with tempfile.TemporaryDirectory() as tmp:
        tiny = make_estimator("depth-anything-v2", str(make_tiny_checkpoint(Path(tmp), image_size=518)))
        rate = images_per_second(tiny, da_batch, args.repeats)
        print(f"depth-anything-v2  tiny random config, 518 px processor, {args.da_resolution}px images "
              f"batch {da_batch.shape[0]}: {rate}")
    if args.da_checkpoint:
        real = make_estimator("depth-anything-v2", args.da_checkpoint)
        rate = images_per_second(real, da_batch, max(1, args.repeats // 2))
        print(f"depth-anything-v2  {args.da_checkpoint}, {args.da_resolution}px images batch "
              f"{da_batch.shape[0]}: {rate}")

    if args.cache_data is not None:
        from depthnerf.data.srn import index_split
        from depthnerf.depth.cache import PriorStore

        store = PriorStore.open(args.cache_data, "bundled", resolution=128)
        group = sorted(p.name for p in store.root.iterdir() if p.is_dir())[0]  # e.g. cars_test
        category, split = group.rsplit("_", 1)
        records = [r for r in index_split(args.cache_data, category, split, check_files=False).objects
                   if (store.root / group / f"{r.object_id}.safetensors").is_file()]
        store.check(records)
        start, calls = time.perf_counter(), 0
        while time.perf_counter() - start < 3.0:
            record = records[calls % len(records)]
            store.load(record, [calls % record.num_views])
            calls += 1
        print(f"PriorStore.load    1 view/call ({group}, {records[0].num_views} views/object): "
              f"{calls / (time.perf_counter() - start):8.1f} calls/s")


if __name__ == "__main__":
    main()
