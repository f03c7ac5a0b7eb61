"""The feature gather at inference, kernel against kernel: prints ms per call, asserts nothing.

On one H100 the gather of pixel-aligned features (``depthnerf.model.features.sample_maps``: ``embedding_bag`` over
the 4 bilinear corners of each point) took a third of a paper-sampler view's GPU time, at ~350 GB/s
(docs/speed.md, "GPU"). This times the candidates on the same input, without autograd, and checks that each gives
the same values as ``sample_maps`` (largest absolute difference, printed):

* ``embedding_bag``: what ``sample_maps`` runs (fp32 maps; and bf16 maps and corner weights, half the bytes);
* ``grid_sample``: ``F.grid_sample`` on channels-first fp32 maps (its forward is deterministic; bf16 would round
  the grid coordinates to ~0.1 feature pixel, so it is not a candidate);
* ``index``: :func:`~depthnerf.model.features.sample_maps_gather`, the ``--deterministic`` training path;
* ``compiled_index``: :meth:`~depthnerf.model.features.MapSamples.read` through ``torch.compile`` (the kernel
  inductor writes for ``--gather inside``, here alone; in a view it is part of the compiled MLP's graph), from fp32
  and from bf16 maps with fp32 coordinates.

    python benchmarks/bench_gather.py                  # CUDA: 2^20 points, 64x64 maps, 512 channels
    python benchmarks/bench_gather.py --points 65536   # CPU-sized
    python benchmarks/bench_gather.py --json out.json  # also write the figures (scripts/gpu_check.py)
"""

from __future__ import annotations

import argparse
import json

import torch
import torch.nn.functional as F
from bench_gpu import timed  # beside this file

from depthnerf.model.features import MapSamples, _corners, sample_maps, sample_maps_gather


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="auto", help="auto, cpu or cuda")
    p.add_argument("--points", type=int, default=1 << 20, help="points per call (inference chunk on CUDA: 2^20)")
    p.add_argument("--size", type=int, default=64, help="feature map side (paper: 64 for 128 px inputs)")
    p.add_argument("--channels", type=int, default=512, help="feature channels (paper's ResNet34 latent: 512)")
    p.add_argument("--repeat", type=int, default=10)
    p.add_argument("--json", metavar="PATH", help="also write the figures to PATH as JSON")
    args = p.parse_args()
    device = torch.device("cuda" if args.device == "auto" and torch.cuda.is_available() else
                          ("cpu" if args.device == "auto" else args.device))
    cuda = device.type == "cuda"
    gen = torch.Generator().manual_seed(0)
    maps = torch.randn(1, args.size, args.size, args.channels, generator=gen).to(device)
    grid = (torch.rand(1, args.points, 2, generator=gen) * 2.2 - 1.1).to(device)  # some points off the map
    maps_cf = maps.permute(0, 3, 1, 2).contiguous()
    maps_bf16 = maps.bfloat16()

    def grid_sample(m):
        return F.grid_sample(m, grid[:, None], align_corners=True, padding_mode="border")[:, :, 0].transpose(1, 2)

    def embedding_bag_bf16():
        index, weight = _corners(grid, 1, args.size, args.size)
        return F.embedding_bag(index, maps_bf16.reshape(-1, args.channels), per_sample_weights=weight.bfloat16(),
                               mode="sum")

    def index_gather(m):
        index, weight = _corners(grid, 1, args.size, args.size)
        return sample_maps_gather(m, index, weight).reshape(1, args.points, -1)

    def read_all(m, g):
        samples = MapSamples(maps=m, grid=g)
        return samples.read(samples.corners())
    compiled_read = torch.compile(read_all, dynamic=False)

    candidates = {
        "embedding_bag_fp32": lambda: sample_maps(maps, grid),
        "embedding_bag_bf16": embedding_bag_bf16,
        "grid_sample_fp32": lambda: grid_sample(maps_cf),
        "index_fp32": lambda: index_gather(maps),
        "compiled_index_fp32": lambda: compiled_read(maps, grid),
        "compiled_index_bf16": lambda: compiled_read(maps_bf16, grid),
    }
    out = {"device": str(device), "points": args.points, "size": args.size, "channels": args.channels,
           "torch": torch.__version__, "gpu": torch.cuda.get_device_name(device) if cuda else None}
    with torch.no_grad():
        reference = sample_maps(maps, grid).float()
        print(f"gather of {args.points} points from a {args.size}x{args.size}x{args.channels} map on {device}:")
        for name, fn in candidates.items():
            try:
                diff = float((fn().float().reshape(reference.shape) - reference).abs().max())  # also the warm-up
                ms = min(timed(fn, args.repeat, device)) * 1e3
            except Exception as err:  # e.g. a dtype a kernel does not take on this device, or no compiler for inductor
                out[name] = {"error": (str(err).splitlines() or [type(err).__name__])[0]}
                print(f"  {name:20s} failed: {out[name]['error']}")
                continue
            moved = args.points * 4 * args.channels * (4 if "fp32" in name else 2)  # 4 corners x bytes per value
            out[name] = {"ms": ms, "max_abs_diff": diff, "gb_per_s_corner_reads": moved / ms / 1e6}
            print(f"  {name:20s} {ms:8.2f} ms  (max |diff| {diff:.2e}, {out[name]['gb_per_s_corner_reads']:.0f} "
                  "GB/s of corner reads)")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
