"""Mesh vertex colours scored against the true views: each colour rule's mesh rendered into the target views.

For each test object, exactly as ``depthnerf eval`` prepares it (input view 64, every ``--views-stride``-th other
view), the mesh is extracted once (``--mesh-resolution``, the ``auto`` level, as reconstruct and the demo) and
coloured by each rule (``depthnerf.render.mesh_colors``: ``point``, ``normal-ray`` at each ``--half-widths`` and
``photo`` with each ``--fills``, at the first half-width).
Each coloured mesh is rendered into every target view by ray casting (the synthetic generator's first-hit engine;
the colour at a hit is the barycentric mix of the triangle's vertex colours, unlit, on white) and scored:

* ``psnr``: the whole image against the ground truth (geometry and colour together);
* ``object_psnr``: on the pixels where the mesh is hit and the ground truth shows the object (colour alone: the
  same mesh, hence the same pixels, for every rule);
* ``delta_ab``: the mean CIELAB (a, b) distance on those pixels (hue and saturation error, lightness left out).

Each metric is averaged over an object's views, then over objects; each rule is paired per object against
``--against`` (default ``point``; mean difference, 95% t interval, objects no worse).

    python scripts/mesh_color_study.py --checkpoint cpu-chairs-sym-pp --data DATA --category chairs --objects 50
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
import torch
import trimesh
from paired_difference import t_interval
from skimage.color import rgb2lab

from depthnerf.data.cameras import Intrinsics, camera_rays
from depthnerf.data.protocol import protocol_views
from depthnerf.data.srn import index_split
from depthnerf.data.symmetry import dataset_plane
from depthnerf.data.synth.hits import first_hit_finder
from depthnerf.eval.objects import prepare_object
from depthnerf.infer.session import InferenceSession, photo_view
from depthnerf.render.mesh import MeshConfig, field_radiance
from depthnerf.render.mesh_colors import NORMAL_RAY, POINT, vertex_colors
from depthnerf.render.mesh_level import AUTO_LEVEL
from depthnerf.render.photo_colors import PHOTO, PHOTO_FILL

METRICS = ("psnr", "object_psnr", "delta_ab")
"""Per-object scores, each an object mean of view values; higher is better except ``delta_ab``."""


def mesh_render(mesh: trimesh.Trimesh, colors: np.ndarray, c2w: torch.Tensor, intr: Intrinsics
                ) -> tuple[np.ndarray, np.ndarray]:
    """(RGB ``(H, W, 3)`` in [0, 1] on white, hit mask ``(H, W)``) of ``mesh`` with per-vertex ``colors``
    ``(P, 3)`` seen from ``c2w``: the first triangle each pixel's centre ray meets, its colour the barycentric mix."""
    origins, dirs = (x.reshape(-1, 3).double().numpy() for x in camera_rays(c2w, intr))
    vertices, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces)
    face = first_hit_finder(vertices, faces)(origins, dirs)
    hit = face >= 0
    a, b, c = (vertices[faces[face[hit]]][:, k] for k in range(3))
    d, s = dirs[hit], origins[hit] - a
    e1, e2 = b - a, c - a
    p, q = np.cross(d, e2), np.cross(s, e1)
    det = (e1 * p).sum(1)
    u, v = (s * p).sum(1) / det, (d * q).sum(1) / det  # Moller-Trumbore barycentrics of the hit
    weights = np.stack([1 - u - v, u, v], axis=1)
    image = np.ones((len(origins), 3))
    image[hit] = (weights[..., None] * colors[faces[face[hit]]]).sum(1)
    return image.reshape(intr.height, intr.width, 3), hit.reshape(intr.height, intr.width)


def view_scores(image: np.ndarray, hit: np.ndarray, gt: np.ndarray, gt_mask: np.ndarray) -> dict[str, float]:
    """The three metrics (module docstring) of one rendered view; ``object_*`` are NaN where no pixel is shared."""
    both = hit & gt_mask
    scores = {"psnr": -10 * math.log10(max(float(((image - gt) ** 2).mean()), 1e-10))}
    if not both.any():
        return {**scores, "object_psnr": math.nan, "delta_ab": math.nan}
    err = float(((image[both] - gt[both]) ** 2).mean())
    lab_r, lab_g = rgb2lab(image[both][None]), rgb2lab(gt[both][None])
    scores["object_psnr"] = -10 * math.log10(max(err, 1e-10))
    scores["delta_ab"] = float(np.hypot(*(lab_r[..., 1:] - lab_g[..., 1:]).transpose(2, 0, 1)).mean())
    return scores


def write_figure(panels: list[tuple[str, list[np.ndarray]]], path: Path, columns: int = 4) -> None:
    """One row per (label, views): ``columns`` of the views, evenly spaced, side by side, labelled on the left."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(panels), columns, figsize=(1.6 * columns + 1.6, 1.6 * len(panels)), squeeze=False)
    for row, (label, views) in zip(axes, panels, strict=True):
        picks = np.linspace(0, len(views) - 1, columns).round().astype(int)
        for ax, k in zip(row, picks, strict=True):
            ax.imshow(np.clip(views[k], 0, 1))
            ax.set_xticks([])
            ax.set_yticks([])
        row[0].set_ylabel(label.replace(" truth", "\ntruth"), fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--category", required=True)
    ap.add_argument("--objects", type=int, default=50, help="the first N test objects")
    ap.add_argument("--views-stride", type=int, default=25)
    ap.add_argument("--mesh-resolution", type=int, default=128, help="as depthnerf reconstruct's default")
    ap.add_argument("--half-widths", type=float, nargs="+", default=[MeshConfig().color_half_width])
    ap.add_argument("--fills", type=float, nargs="+", default=[0.0, PHOTO_FILL],
                    help="photo rule: its fill values (at the first half-width)")
    ap.add_argument("--against", default=POINT, help="the rule every other is paired with (a name of the table)")
    ap.add_argument("--out", type=Path, help="per-object scores as JSON")
    ap.add_argument("--figure", type=Path, help="a PNG: the truth and each rule's mesh in four target views")
    ap.add_argument("--figure-objects", type=int, default=3, help="objects (the first ones) in --figure")
    ap.add_argument("--figure-rules", nargs="+", help="the rules (names of the table) --figure shows (default: all)")
    args = ap.parse_args(argv)
    session = InferenceSession(args.checkpoint)
    plane = dataset_plane(args.data, args.category)[0] if session.model.cfg.mirror else None
    half = args.half_widths[0]
    rules = [(POINT, 0.0, 0.0)] + [(NORMAL_RAY, h, 0.0) for h in args.half_widths] + \
        [(PHOTO, half, f) for f in args.fills]
    names = [POINT] + [f"{NORMAL_RAY} {h:g}" for h in args.half_widths] + [f"{PHOTO} fill {f:g}" for f in args.fills]
    for name in [args.against, *(args.figure_rules or [])]:
        if name not in names:
            ap.error(f"rule names are {', '.join(names)}, got {name!r}")
    shown = [n for n in names if n in (args.figure_rules or names)]  # in the table's order
    rows: dict[str, dict[str, dict[str, float]]] = {}
    panels: list[tuple[str, list[np.ndarray]]] = []
    for record in index_split(args.data, args.category, "test").objects[:args.objects]:
        obj = prepare_object(session, record, protocol_views(record.num_views, args.views_stride),
                             symmetry_plane=plane)
        cfg = MeshConfig(args.mesh_resolution, AUTO_LEVEL)
        mesh, _ = session.mesh(obj.encoded, cfg, colored=False)
        if len(mesh.faces) == 0:
            print(f"{record.object_id}: empty mesh, left out", file=sys.stderr)
            continue
        radiance = field_radiance(session.model, obj.encoded.enc, session.runtime)
        gts = obj.targets.images.permute(0, 2, 3, 1).numpy()
        masks = obj.targets.masks.numpy()
        rows[record.object_id] = {}
        with torch.no_grad():
            for name, (rule, width, fill) in zip(names, rules, strict=True):
                rgba = vertex_colors(rule, radiance, mesh, obj.encoded.pose[:3, 3], width or cfg.color_half_width,
                                     cfg.color_samples, cfg.chunk, session.device, photo_view(obj.encoded), fill)
                renders = [mesh_render(mesh, rgba[:, :3] / 255.0, pose, obj.targets.intrinsics)
                           for pose in obj.targets.poses]
                views = [view_scores(*r, gt, m) for r, gt, m in zip(renders, gts, masks, strict=True)]
                if len(rows) <= args.figure_objects and name in shown:
                    if name == shown[0]:
                        panels.append((f"{record.object_id} truth", list(gts)))
                    panels.append((name, [r[0] for r in renders]))
                rows[record.object_id][name] = {k: float(np.nanmean([v[k] for v in views])) for k in METRICS}
        print(record.object_id, " ".join(f"{n}: {rows[record.object_id][n]['object_psnr']:.2f}" for n in names),
              file=sys.stderr, flush=True)
    print(f"{args.checkpoint} on {len(rows)} {args.category} ({args.data}), mesh resolution {args.mesh_resolution}")
    print("| rule | " + " | ".join(METRICS) + " | " + " | ".join(f"{m} vs {args.against}" for m in METRICS) + " |")
    print("|---" * (1 + 2 * len(METRICS)) + "|")
    for name in names:
        means = [np.mean([r[name][m] for r in rows.values()]) for m in METRICS]
        cells = [f"{x:.3f}" for x in means]
        for m in METRICS if name != args.against else ():
            diffs = [r[name][m] - r[args.against][m] for r in rows.values()]
            mean, _, half = t_interval(diffs)
            better = sum((d >= 0) if m != "delta_ab" else (d <= 0) for d in diffs)
            cells.append(f"{mean:+.3f} [{mean - half:+.3f}, {mean + half:+.3f}], {better}/{len(diffs)}")
        print(f"| {name} | " + " | ".join(cells + [""] * (2 * len(METRICS) - len(cells))) + " |")
    if args.out:
        args.out.write_text(json.dumps(rows, indent=1) + "\n")
    if args.figure:
        write_figure(panels, args.figure)
    return 0


if __name__ == "__main__":
    sys.exit(main())
