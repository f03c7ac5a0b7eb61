"""Where do the depth-aware model's white floaters come from? Probe a trained checkpoint at inference time.

For the first N test objects of a dataset (SRN protocol: view 64 in, every ``--stride``-th other view out), the
checkpoint is run under several *conditions* that change one input of the field at a time, and each condition
reports, averaged over objects:

- ``psnr``: PSNR of the target views;
- ``floaters``: floater fraction of the input-camera mesh (depthnerf.eval.geometry_metrics.floater_fraction);
- ``floaters_near``: the part of it between the object and the input camera (``scripts/floater_sides.py``);
- ``src_bg_opacity``: mean rendered opacity of the INPUT view's own background pixels (the input view sees empty
  space there, so any opacity on those rays is density the evidence contradicts);
- ``src_bg_white_error``: mean |rendered colour - white| on those same pixels (what the L2 colour loss sees of
  that density when the view is a training target: near 0 when the density is white);
- ``tgt_bg_opacity``: mean rendered opacity on the target views' background pixels.

Conditions (a depth-aware checkpoint; the baseline gets ``as-trained`` and ``bn-batch-stats`` only):
``as-trained`` (the checkpoint as evaluated); ``bn-batch-stats`` (encoder BatchNorm with the input image's own
statistics, as in training, instead of the running averages); ``oracle-prior`` (the ground-truth 1/z prior, the
same normalisation); ``flat-prior`` (foreground prior 0: the mask alone); ``no-mask-prior`` (every pixel the
background constant: no depth information and no mask).

    python scripts/floater_probe.py --checkpoint cpu-cars-depth --data study/data --objects 8 --json out.json
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import torch
from floater_sides import AXES, card_up_axis, side_fractions

from depthnerf.data.card import read_dataset_card
from depthnerf.data.mesh_file import read_mesh
from depthnerf.data.srn import index_split
from depthnerf.depth.normalize import BACKGROUND_VALUE
from depthnerf.depth.prior import PriorConfig, open_prior
from depthnerf.eval.geometry_metrics import GeometryConfig, floater_fraction, is_empty_mesh, sample_surface
from depthnerf.eval.metrics import psnr
from depthnerf.eval.objects import prepare_object, protocol_views
from depthnerf.infer.session import InferenceSession, SessionOptions
from depthnerf.model.conditioning import condition_views
from depthnerf.pretrained.load import load_pretrained
from depthnerf.render.mesh import MeshConfig, input_camera_mesh
from depthnerf.render.views import render_poses

DEPTH_CONDITIONS = ("as-trained", "bn-batch-stats", "oracle-prior", "flat-prior", "no-mask-prior")
BASELINE_CONDITIONS = ("as-trained", "bn-batch-stats")


def batch_stats_model(model: torch.nn.Module) -> torch.nn.Module:
    """A copy whose encoder BatchNorm layers normalise with the input's own statistics (training behaviour)."""
    twin = copy.deepcopy(model)
    for module in twin.encoder.modules():
        if isinstance(module, torch.nn.BatchNorm2d):
            module.train()
            module.momentum = 0.0
    return twin


def conditioned_prior(name: str, prior: torch.Tensor, masks: torch.Tensor, oracle: torch.Tensor | None) -> torch.Tensor:
    """The encoder's prior channel [1, V, 1, H, W] under a condition."""
    if name == "oracle-prior":
        return oracle
    if name == "flat-prior":
        return torch.where(masks[None, :, None].to(prior.device), torch.zeros_like(prior), prior)
    if name == "no-mask-prior":
        return torch.full_like(prior, BACKGROUND_VALUE)
    return prior


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--objects", type=int, default=8)
    ap.add_argument("--stride", type=int, default=25)
    ap.add_argument("--mesh-resolution", type=int, default=96)
    ap.add_argument("--conditions", nargs="+", help="a subset of the conditions (default: all that apply)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    pre = load_pretrained(args.checkpoint)
    records = index_split(args.data, pre.spec.category, "test").objects[: args.objects]
    session = InferenceSession(pre, SessionOptions(inputs="dataset", data_root=args.data, records=records))
    spec, model = session.spec, session.model
    near, far = spec.z_range
    depth_aware = spec.prior.enabled
    conditions = DEPTH_CONDITIONS if depth_aware else BASELINE_CONDITIONS
    if args.conditions:
        unknown = sorted(set(args.conditions) - set(conditions))
        if unknown:
            raise SystemExit(f"error: --conditions {unknown[0]}: choose from {', '.join(conditions)}")
        conditions = tuple(args.conditions)
    oracle = open_prior(PriorConfig("oracle"), data_root=args.data, resolution=spec.resolution, records=records)
    twin = batch_stats_model(model)
    card = read_dataset_card(args.data, pre.spec.category) or {}
    up = AXES[card_up_axis(card) or "z"]
    rows: dict[str, list[dict]] = {c: [] for c in conditions}
    for record in records:
        obj = prepare_object(session, record, protocol_views(record.num_views, args.stride))
        src, tgt = obj.source, obj.targets
        oracle_prior = condition_views(oracle, src).inputs.disparity if depth_aware else None
        gt_mesh = read_mesh(record.mesh_path)
        for name in conditions:
            net = twin if name == "bn-batch-stats" else model
            inputs = obj.encoded.inputs
            if depth_aware:
                inputs = dataclasses.replace(inputs, disparity=conditioned_prior(name, inputs.disparity, src.masks,
                                                                                 oracle_prior))
            with torch.no_grad():
                enc = net.encode(inputs)
                own = render_poses(net, enc, src.poses, src.intrinsics, near, far, spec.render, 4096, "cpu")
                out = render_poses(net, enc, tgt.poses, tgt.intrinsics, near, far, spec.render, 4096, "cpu")
                mesh, _ = input_camera_mesh(net, enc, src.poses[0], src.intrinsics, near, far,
                                            MeshConfig(args.mesh_resolution, "auto"), "cpu", colored=False)
            gts = tgt.images.permute(0, 2, 3, 1)
            geometry = GeometryConfig(n_points=20_000)
            points = None if is_empty_mesh(mesh) else sample_surface(mesh, geometry.n_points, geometry.seed)
            sides = side_fractions(mesh, gt_mesh, src.poses[0][:3, 3].double().numpy(), up, geometry, points)
            rows[name].append({
                "psnr": float(np.mean([psnr(out.rgb[k].numpy(), gts[k].numpy()) for k in range(len(gts))])),
                "floaters": floater_fraction(mesh, gt_mesh, geometry, points),
                "floaters_near": sides["near"],
                "src_bg_opacity": float(own.opacity[~src.masks].mean()),
                "src_bg_white_error": float((1.0 - own.rgb[~src.masks]).abs().mean()),
                "tgt_bg_opacity": float(out.opacity[~tgt.masks].mean()),
            })
        print(record.object_id, {c: {k: round(v, 3) for k, v in rows[c][-1].items()} for c in conditions},
              flush=True)
    means = {c: {k: float(np.mean([r[k] for r in rows[c]])) for k in rows[c][0]} for c in conditions}
    print(f"{args.checkpoint}: {len(records)} objects")
    print("| condition | PSNR | floater fraction | of it near the input camera | input-view background opacity "
          "| its colour error | target background opacity |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for c, m in means.items():
        print(f"| {c} | {m['psnr']:.2f} | {m['floaters']:.3f} | {m['floaters_near']:.3f} | "
              f"{m['src_bg_opacity']:.3f} | "
              f"{m['src_bg_white_error']:.4f} | {m['tgt_bg_opacity']:.3f} |")
    if args.json:
        args.json.write_text(json.dumps({"checkpoint": args.checkpoint, "objects": len(records), "means": means,
                                         "per_object": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
