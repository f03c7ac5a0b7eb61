"""Seconds for mesh extraction on a 128^3 grid with a cheap analytic density, and for Chamfer/F-score.

    python benchmarks/bench_mesh.py [--resolution 128] [--repeats 3] [--points 100000]

Prints, per step, the best of ``--repeats`` wall-clock times (CPU, this process's torch thread count): density
sampling over the grid (chunked queries; the analytic density costs almost nothing, so this is the grid
overhead a model query adds to), marching cubes, the whole ``extract_mesh``, and ``geometry_metrics`` at
``--points`` samples per mesh. The model-driven timing (density from PixelNeRF) is added by the training stage.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
import trimesh
from skimage.measure import marching_cubes

from depthnerf.data.cameras import Intrinsics, look_at
from depthnerf.eval.geometry_metrics import GeometryConfig, geometry_metrics
from depthnerf.render.mesh import CameraGrid, MeshConfig, extract_mesh, sample_density


def best_of(repeats: int, fn) -> tuple[float, object]:
    """Fastest wall-clock seconds of ``repeats`` calls, and the last result."""
    times, out = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - start)
    return min(times), out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--points", type=int, default=100_000)
    args = parser.parse_args()

    radius = 0.4

    def density(p: torch.Tensor) -> torch.Tensor:
        return 40.0 * torch.sigmoid((radius - p.norm(dim=-1)) / 0.02)

    config = MeshConfig(resolution=args.resolution)
    cube = CameraGrid.world_box((-0.6,) * 3, (0.6,) * 3)
    frustum = CameraGrid.from_frustum(look_at(torch.tensor([1.3, 0.0, 0.0])),
                                      Intrinsics(131.25, 63.5, 63.5, 128, 128), 0.8, 1.8)  # SRN cars camera
    print(f"torch threads {torch.get_num_threads()}, resolution {args.resolution}, best of {args.repeats}")
    for name, grid in (("cube", cube), ("cars frustum", frustum)):
        shape = grid.layout(args.resolution)[0]
        n = int(np.prod(shape))
        t_sample, vol = best_of(args.repeats, lambda g=grid: sample_density(density, g, config))
        t_mc, (verts, faces, _, _) = best_of(args.repeats, lambda v=vol: marching_cubes(
            v.values, level=config.threshold, spacing=(v.step,) * 3, gradient_direction="ascent"))
        t_total, mesh = best_of(args.repeats, lambda g=grid: extract_mesh(density, g, config))
        print(f"{name:13s} grid {shape[0]}x{shape[1]}x{shape[2]} ({n / 1e6:.2f}M points): sample {t_sample:.2f}s "
              f"({n / t_sample / 1e6:.1f}M pts/s), marching cubes {t_mc:.2f}s, extract_mesh {t_total:.2f}s, "
              f"{len(mesh.faces)} faces")

    gt = trimesh.creation.icosphere(subdivisions=5, radius=radius)
    geo = GeometryConfig(n_points=args.points)
    t_geo, result = best_of(args.repeats, lambda: geometry_metrics(mesh, gt, geo))
    print(f"geometry_metrics ({args.points} points per mesh): {t_geo:.2f}s, chamfer_l1 {result.chamfer_l1:.5f} "
          f"(GT diagonals), fscore@{geo.tau} {result.fscore:.3f}")


if __name__ == "__main__":
    main()
