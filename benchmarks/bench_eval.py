"""Seconds for the SRN protocol on one object (250 target views) and for a 128^3 mesh extraction, CPU presets.

    python benchmarks/bench_eval.py [--preset cpu-cars] [--checkpoint PATH] [--views 250] [--resolution R]
                                    [--mesh-resolution 128] [--chunk 4096] [--threads N]

Uses the same functions as ``depthnerf eval`` (:func:`depthnerf.reconstruct.orbit.render_poses`,
:func:`depthnerf.eval.metrics.object_metrics`, :func:`depthnerf.reconstruct.orbit.field_queries` +
:func:`depthnerf.render.mesh.extract_mesh`). Without ``--checkpoint`` the model is built from the preset's config
with random weights (timing does not depend on the weights; the depth-aware preset is used, whose encoder also
takes the prior). The object is synthetic: a grey input image with a random prior, target cameras on SRN-like
orbits. Prints one line per stage: encode once, render N views (and rays/s), PSNR+SSIM over N views, mesh
(density queries + marching cubes) on the input camera's frustum grid.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from depthnerf.cpu_runtime import keep_freed_memory
from depthnerf.data.srn import category_defaults
from depthnerf.eval.metrics import object_metrics
from depthnerf.model.pixelnerf import PixelNeRF, SourceViews
from depthnerf.reconstruct.orbit import orbit_poses, srn_intrinsics
from depthnerf.render.mesh import CameraGrid, MeshConfig, extract_mesh, field_queries
from depthnerf.render.views import render_poses
from depthnerf.train.config import inference_spec, preset


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="cpu-cars", help="preset whose model/renderer is timed")
    parser.add_argument("--checkpoint", help="time this checkpoint instead of random weights")
    parser.add_argument("--views", type=int, default=250, help="target views (SRN protocol: 250)")
    parser.add_argument("--resolution", type=int, help="render resolution (default: the training resolution)")
    parser.add_argument("--mesh-resolution", type=int, default=128)
    parser.add_argument("--chunk", type=int, default=4096)
    parser.add_argument("--threads", type=int, help="torch threads (default: torch's choice)")
    args = parser.parse_args()
    keep_freed_memory()  # as the depthnerf CLI does (depthnerf.cpu_runtime)
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.checkpoint:
        from depthnerf.pretrained.load import load_pretrained

        pre = load_pretrained(args.checkpoint)
        model, spec, label = pre.model, pre.spec, args.checkpoint
    else:
        spec = inference_spec(preset(args.preset))
        torch.manual_seed(0)
        model, label = PixelNeRF(spec.model, depth_aware=spec.depth_aware).eval(), f"{args.preset} (random weights)"
    cfg = spec
    cat = category_defaults(spec.category)
    res_in, res = spec.resolution, args.resolution or spec.resolution
    near, far = spec.z_range
    intr_in, intr = srn_intrinsics(cat.focal, cat.image_size, res_in), srn_intrinsics(cat.focal, cat.image_size, res)
    poses = torch.cat([orbit_poses(cat.camera_radius, e, -(-args.views // 3), 7.0 * k)
                       for k, e in enumerate((15.0, 30.0, 45.0))])[: args.views]
    src_pose = orbit_poses(cat.camera_radius, 30.0, 1)
    gen = torch.Generator().manual_seed(0)
    disparity = torch.randn(1, 1, 1, res_in, res_in, generator=gen) if spec.depth_aware else None
    src = SourceViews(images=torch.full((1, 1, 3, res_in, res_in), 0.5), poses=src_pose[None],
                      focal=torch.tensor([intr_in.focal]), principal=torch.tensor([[intr_in.cx, intr_in.cy]]),
                      disparity=disparity)
    s = cfg.render.sampler
    print(f"{label}: torch threads {torch.get_num_threads()}, {args.views} views at {res}x{res} (input {res_in}), "
          f"samples {s.n_coarse} coarse + {s.n_coarse + s.n_importance + s.n_gaussian} fine, "
          f"MLP width {cfg.model.coarse.d_hidden}, chunk {args.chunk}")
    with torch.no_grad():
        t = time.perf_counter()
        enc = model.encode(src)
        t_enc = time.perf_counter() - t
        t = time.perf_counter()
        out = render_poses(model, enc, poses, intr, near, far, cfg.render, args.chunk, "cpu")
        t_render = time.perf_counter() - t
    rays = args.views * res * res
    print(f"encode once: {t_enc:.3f} s")
    print(f"render {args.views} views: {t_render:.1f} s ({rays / t_render:.0f} rays/s, "
          f"{t_render / args.views:.2f} s/view)")
    gts = np.random.default_rng(0).uniform(0, 1, (args.views, res, res, 3))
    t = time.perf_counter()
    object_metrics("bench", out.rgb.numpy(), gts)
    print(f"PSNR+SSIM over {args.views} views: {time.perf_counter() - t:.2f} s")
    density_fn, _ = field_queries(model, enc, src_pose[0, :3, 3])
    grid = CameraGrid.from_frustum(src_pose[0], intr_in, near, far)
    shape = grid.layout(args.mesh_resolution)[0]
    t = time.perf_counter()
    mesh = extract_mesh(density_fn, grid, MeshConfig(resolution=args.mesh_resolution))
    t_mesh = time.perf_counter() - t
    n = int(np.prod(shape))
    print(f"mesh {shape[0]}x{shape[1]}x{shape[2]} grid ({n / 1e6:.2f}M points): {t_mesh:.1f} s "
          f"({n / t_mesh:.0f} points/s), {len(mesh.faces)} faces")
    print(f"total for one object (encode + render + metrics + mesh): about "
          f"{t_enc + t_render + t_mesh:.0f} s + metrics")


if __name__ == "__main__":
    main()
