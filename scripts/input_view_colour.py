"""Does a model give back the input's colours? Render the input view itself and views near it, and measure.

For each of the first ``--objects`` test objects the model is conditioned on view 64 (as ``depthnerf eval`` does)
and renders view 64 itself plus every ``--every``-th of the ``--nearest`` views closest to it (by the angle between
their optical axes, as ``scripts/angle_bins.py`` bins views). Per angle bin it prints PSNR and, on the ground truth's object
pixels, the CIELAB chroma of render and truth and their mean ``(a, b)`` distance (``scripts/colour_fidelity.py``'s
``delta ab``). At 0 degrees every visible surface point projects to its own input pixel, so a model that reads
colour from its input should match it there best. ``--surface`` also queries the fine network at the true surface
of the input view (its ground-truth depth) and compares that colour, and the render's, with the truth on the same
pixels: whether the hue is lost in the field itself or in compositing. ``--figure`` writes, at the input view for
the first objects, truth | render | 3x |difference|, or with several checkpoints truth | each one's render.

    python scripts/input_view_colour.py --checkpoint cpu-chairs-sym-pp --data DATA --objects 12
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch
from angle_bins import axis_angle, optical_axis
from colour_fidelity import view_colour

from depthnerf.data.protocol import INPUT_VIEW, ProtocolViews
from depthnerf.data.srn import index_split
from depthnerf.eval.metrics import psnr
from depthnerf.eval.objects import prepare_object
from depthnerf.infer.session import InferenceSession, SessionOptions
from depthnerf.model.config import ENCODER_NORMS
from depthnerf.pretrained.load import load_pretrained
from depthnerf.render.rays import camera_z_of_directions, rays_from_camera


def surface_colour(session: InferenceSession, obj, record, render: np.ndarray, white: float) -> dict | None:
    """Delta ab against the truth, on the input view's object pixels with a ground-truth depth, of the fine
    network's colour at the true surface point of each pixel and of the rendered colour ``render`` (None: no such
    pixel)."""
    truth_view = session.load_views(record, [INPUT_VIEW], session.spec.resolution, with_depth=True)
    depth = truth_view.depths[0].reshape(-1)
    truth = truth_view.images[0].permute(1, 2, 0).reshape(-1, 3).numpy().astype(np.float64)
    on = (depth > 0).numpy() & (truth < white).any(-1)
    if not on.any():
        return None
    near, far = session.spec.z_range
    rays = rays_from_camera(truth_view.poses[:1], truth_view.intrinsics, near, far)
    distance = depth[None] / camera_z_of_directions(rays.directions, truth_view.poses[:1])
    points = rays.origins + rays.directions * distance[..., None]
    rgb, _ = session.model.field(obj.encoded.enc, "fine")(points[:, :, None, :], rays.directions)
    field = rgb[0, :, 0].double().numpy()
    flat = render.reshape(-1, 3)
    return {"field_delta_ab": view_colour(field[on][None], truth[on][None], 2.0)[2],
            "render_delta_ab": view_colour(flat[on][None], truth[on][None], 2.0)[2], "pixels": int(on.sum())}


def measure(checkpoint: str, args: argparse.Namespace) -> tuple[list[dict], list[np.ndarray], list[np.ndarray]]:
    """Per rendered view: object, view, angle, PSNR and the colour measures; and the truth and the render at the
    input view of the first ``args.figure_objects`` objects."""
    pre = load_pretrained(checkpoint)
    records = index_split(args.data, pre.spec.category, "test").objects[: args.objects]
    session = InferenceSession(pre, SessionOptions(inputs="dataset", data_root=args.data, records=records,
                                                   encoder_norm=args.encoder_norm))
    plane, _ = session.dataset_symmetry(pre.spec.category)
    rows, truths, renders = [], [], []
    with torch.no_grad():
        for k, record in enumerate(records):
            axis = optical_axis(record, INPUT_VIEW)
            angles = [axis_angle(axis, optical_axis(record, v)) for v in range(record.num_views)]
            pick = sorted(range(record.num_views), key=angles.__getitem__)[: args.nearest : args.every]
            loaded = sorted(pick)  # targets in index order (ProtocolViews); rows below in order of angle
            obj = prepare_object(session, record, ProtocolViews((INPUT_VIEW,), tuple(loaded), record.num_views - 1),
                                 symmetry_plane=plane)
            out = session.render(obj.encoded, obj.targets.poses, obj.targets.intrinsics)
            for i in pick:
                j = loaded.index(i)
                render = out.rgb[j].numpy().astype(np.float64)
                truth = obj.targets.images[j].permute(1, 2, 0).numpy().astype(np.float64)
                colour = view_colour(render, truth, args.white)
                rows.append({"object": record.object_id, "view": i, "angle": angles[i], "psnr": psnr(render, truth),
                             **({} if colour is None else dict(zip(("chroma", "gt_chroma", "delta_ab"), colour,
                                                                    strict=True)))})
                if i == INPUT_VIEW and args.surface:
                    rows[-1]["surface"] = surface_colour(session, obj, record, render, args.white)
                if i == INPUT_VIEW and k < args.figure_objects:
                    truths.append(truth)
                    renders.append(render)
    return rows, truths, renders


def bin_table(rows: list[dict], bins: list[float]) -> list[dict]:
    """Means of PSNR and the colour measures per angle bin ``[lo, hi)`` (bins without object pixels left out)."""
    table = []
    for lo, hi in zip(bins[:-1], bins[1:], strict=False):
        inside = [r for r in rows if lo <= r["angle"] < hi and "delta_ab" in r]
        if inside:
            table.append({"bin": [lo, hi], "views": len(inside),
                          **{key: float(np.mean([r[key] for r in inside]))
                             for key in ("psnr", "chroma", "gt_chroma", "delta_ab")}})
    return table


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--checkpoint", required=True, nargs="+")
    ap.add_argument("--data", required=True)
    ap.add_argument("--objects", type=int, default=12)
    ap.add_argument("--nearest", type=int, default=40, help="views closest to the input considered")
    ap.add_argument("--every", type=int, default=4, help="render every k-th of them (the input view always)")
    ap.add_argument("--bins", type=float, nargs="+", default=[0, 0.5, 10, 20, 40])
    ap.add_argument("--white", type=float, default=0.95, help="object pixels: any ground-truth channel below this")
    ap.add_argument("--surface", action="store_true", help="also the field's colour at the true surface")
    ap.add_argument("--encoder-norm", choices=ENCODER_NORMS, default="running",
                    help="the encoder's BatchNorm statistics: running (evaluation's) or each image's own (training's)")
    ap.add_argument("--figure", type=Path)
    ap.add_argument("--figure-objects", type=int, default=6)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    results, columns = {}, []
    print("| checkpoint | angle (deg) | views | PSNR | chroma | ground-truth chroma | delta ab |\n"
          "|---|---|---:|---:|---:|---:|---:|")
    for checkpoint in args.checkpoint:
        rows, truths, renders = measure(checkpoint, args)
        results[checkpoint] = {"bins": bin_table(rows, args.bins), "views": rows}
        for b in results[checkpoint]["bins"]:
            lo, hi = b["bin"]
            print(f"| {checkpoint} | {lo:g}-{hi:g} | {b['views']} | {b['psnr']:.2f} | {b['chroma']:.2f} | "
                  f"{b['gt_chroma']:.2f} | {b['delta_ab']:.2f} |")
        surface = [r["surface"] for r in rows if r.get("surface")]
        if surface:
            field, rendered = (float(np.mean([x[key] for x in surface])) for key in ("field_delta_ab",
                                                                                        "render_delta_ab"))
            results[checkpoint]["surface"] = {"objects": len(surface), "field_delta_ab": field,
                                              "render_delta_ab": rendered}
            print(f"{checkpoint}: at the input view's true surface ({len(surface)} objects), the field's colour "
                  f"has delta ab {field:.2f}, the render's {rendered:.2f} on the same pixels")
        if not columns:
            columns.append(truths)
        columns.append(renders)
    if len(args.checkpoint) == 1 and columns:
        columns.append([np.abs(r - t) * 3 for t, r in zip(columns[0], columns[1], strict=True)])
    if args.figure is not None and columns and columns[0]:
        image = np.concatenate([np.concatenate(row, axis=1) for row in zip(*columns, strict=True)], axis=0)
        image = (np.clip(image, 0, 1) * 255).round().astype(np.uint8)
        iio.imwrite(args.figure, np.kron(image, np.ones((3, 3, 1), np.uint8)))
        print(f"wrote {args.figure}")
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
