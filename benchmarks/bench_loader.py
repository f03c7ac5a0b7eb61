"""Training-data loader speed: ms per training item (one object) decoded from the PNG files against read from the
view store (``--data.view_store``, :mod:`depthnerf.data.view_store`), and steps per second of the real DataLoader
with W workers for both.

    python benchmarks/bench_loader.py                      # makes 4 synthetic cars x 50 views at 128 px first
    python benchmarks/bench_loader.py --data data/srn --category cars --workers 8 --json out.json

Items are built exactly as ``depthnerf train`` builds them (the preset's rays, target views, pixel centre and
bounding-box steps; the same keys for both paths, so the same work). Per-item figures run in this process with
one torch thread; the DataLoader figure (``--workers``, 0 to skip) is the steady rate after its first batch, the
whole 4-object step at the preset's size. Run it on an idle machine: the figures are CPU time.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from torch.utils.data import DataLoader


def synth(out: Path, resolution: int, objects: int, views: int) -> None:
    subprocess.run([sys.executable, "-m", "depthnerf", "synth", "--category", "cars", "--out", str(out),
                    "--train-objects", str(objects), "--val-objects", "0", "--test-objects", "0", "--resolution",
                    str(resolution), "--views-train", str(views), "--seed", "0", "--quiet"], check=True)


def main() -> None:
    from depthnerf.data.srn import index_split
    from depthnerf.data.view_store import ViewStore
    from depthnerf.depth.prior import open_prior
    from depthnerf.train.batching import BatchPlan, StepSampler, collate_packed, step_keys
    from depthnerf.train.config import preset
    from depthnerf.train.items import TrainItems

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, help="dataset root (default: make synthetic cars in a temporary folder)")
    p.add_argument("--category", default="cars")
    p.add_argument("--preset", default="paper-cars")
    p.add_argument("--depth", default="none", choices=["none", "oracle", "bundled"],
                   help="prior (oracle reads depth/; bundled reads the cache, made first if missing)")
    p.add_argument("--resolution", type=int, default=128)
    p.add_argument("--objects", type=int, default=4, help="synthetic objects to make without --data")
    p.add_argument("--views", type=int, default=50, help="views per synthetic object (SRN train: 50)")
    p.add_argument("--steps", type=int, default=25, help="steps of items to time per path")
    p.add_argument("--workers", type=int, default=2, help="DataLoader workers for the loader figure (0: skip)")
    p.add_argument("--store", type=Path, help="view store folder (default: a temporary one)")
    p.add_argument("--json", type=Path)
    args = p.parse_args()
    torch.set_num_threads(1)
    tmp = tempfile.TemporaryDirectory(prefix="bench-loader-")
    root = args.data
    if root is None:
        root = Path(tmp.name) / "data"
        synth(root, args.resolution, args.objects, args.views)
    cfg = preset(args.preset)
    if args.depth == "bundled" and not (root / "depth_priors").exists():
        subprocess.run([sys.executable, "-m", "depthnerf", "depth", "--data", str(root), "--depth", "bundled",
                        "--resolution", str(args.resolution)], check=True)
    records = index_split(root, args.category, "train").objects
    prior = open_prior(cfg.prior.override(depth=args.depth), data_root=root, resolution=args.resolution,
                       records=records)
    store_dir = args.store or Path(tmp.name) / "store"
    store = ViewStore(store_dir, args.resolution, cfg.data.pixel_center)
    t0 = time.perf_counter()
    counts = store.ensure(records)
    build_s = time.perf_counter() - t0
    size_mb = sum(f.stat().st_size for f in store_dir.rglob("*") if f.is_file()) / 1e6
    s = cfg.schedule
    plan = BatchPlan(num_objects=len(records), seed=0, bbox_steps=s.bbox_steps, objects_phase1=s.objects_phase1,
                     objects_phase2=s.objects_phase2)
    common = dict(resolution=args.resolution, target_views=cfg.data.target_views, rays_per_object=s.rays_per_object,
                  target_priors=s.depth_loss_weight > 0, pixel_center=cfg.data.pixel_center)
    paths = {"files": TrainItems(records, prior, **common),
             "view_store": TrainItems(records, prior, **common, view_store=store)}
    keys = [k for step in range(args.steps) for k in step_keys(plan, step)]
    result = {"data": str(root), "objects": len(records), "views_per_object": records[0].num_views,
              "resolution": args.resolution, "preset": args.preset, "depth": args.depth,
              "store_build_s": round(build_s, 2), "store_counts": counts, "store_mb": round(size_mb, 1),
              "objects_per_step": plan.batch_size(0), "paths": {}}
    for name, items in paths.items():
        items[keys[0]]  # first touch: imports, page cache
        times = []
        for key in keys:
            t = time.perf_counter()
            items[key]
            times.append(time.perf_counter() - t)
        row = {"ms_per_item_median": round(1e3 * statistics.median(times), 2),
               "ms_per_item_mean": round(1e3 * statistics.fmean(times), 2)}
        if args.workers > 0:
            loader = DataLoader(items, batch_sampler=StepSampler(plan, 0, args.steps * 4), collate_fn=collate_packed,
                                num_workers=args.workers, prefetch_factor=4)
            it = iter(loader)
            next(it)
            t, n = time.perf_counter(), 0
            for packed in it:
                packed.to("cpu")  # what the training loop does with a worker's batch: views of its bytes
                n += 1
            row[f"loader_ms_per_step_{args.workers}_workers"] = round(1e3 * (time.perf_counter() - t) / max(n, 1), 1)
        result["paths"][name] = row
        print(f"{name:10s} {row}", flush=True)
    print(f"view store: built in {build_s:.1f} s, {size_mb:.1f} MB for {len(records)} objects x "
          f"{records[0].num_views} views at {args.resolution} px")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    tmp.cleanup()


if __name__ == "__main__":
    main()
