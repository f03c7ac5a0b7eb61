"""The legs of a chair, as geometry: precision, recall and F-score of the extracted surface in the bottom band of
the object, paired per object.

The eval's F-score is dominated by a chair's seat and back (most of its surface). This script asks whether the
legs are there: it keeps only the points in the bottom ``--band`` of the ground-truth object's height along the
dataset's up axis (default 0.35: below the seat of every synthetic chair archetype, whose seat tops lie at 40-75%
of the height; ``depthnerf/data/synth/chairs.py``) and scores them as the eval scores the whole object
(``depthnerf.eval.geometry_metrics``: the same ground truth, the visible surface back-projected from the object's
depth maps; the same surface samples of the predicted mesh; distances in ground-truth bounding-box diagonals):

- ``band_recall``: the share of the ground truth's band points within ``tau`` of the predicted surface (legs
  found);
- ``band_precision``: the share of the prediction's band points within ``tau`` of the ground truth (a blob that
  fills the space between the legs is not a leg); 0 when the prediction has no surface in the band;
- ``band_fscore``: their harmonic mean.

Every ``--method`` folder is paired per object with ``--baseline`` (mean difference, 95% t-interval, no-worse
count).

    python scripts/leg_geometry.py --baseline study128/eval64/chairs-none-128px \
        --method study128/eval64/chairs-bundled-128px [--band 0.35] [--tau 0.01] [--json OUT]

Needs ``depthnerf eval`` folders with meshes (``meshes/<object_id>.ply``) and the dataset they were scored on.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np
import trimesh
from floater_sides import AXES, eval_mesh, eval_summary
from paired_difference import t_interval

from depthnerf.data.srn import index_split
from depthnerf.eval.geometry_metrics import (
    GeometryConfig,
    is_empty_mesh,
    nearest_distances,
    sample_surface,
    visible_surface_points,
)

METRICS = ("band_precision", "band_recall", "band_fscore")


def band_scores(pred_points: np.ndarray, gt_points: np.ndarray, lo: np.ndarray, hi: np.ndarray, up: int,
                band: float, tau: float) -> dict[str, float]:
    """Precision / recall / F-score of the points below ``lo[up] + band * (hi[up] - lo[up])``.

    ``pred_points`` and ``gt_points``: surface samples in the world frame (``pred_points`` may be empty);
    ``lo, hi``: the ground-truth object's bounds; ``tau`` in ground-truth bounding-box diagonals. Distances are
    to ALL points of the other set, so a leg point near the seat's underside is not penalised by the cut."""
    diagonal = float(np.linalg.norm(hi - lo))
    cut = lo[up] + band * (hi[up] - lo[up])
    gt_band = gt_points[gt_points[:, up] < cut]
    if len(gt_band) == 0:
        raise ValueError(f"no ground-truth point below {band:g} of the height")
    if len(pred_points) == 0:
        return {"band_precision": 0.0, "band_recall": 0.0, "band_fscore": 0.0}
    pred_band = pred_points[pred_points[:, up] < cut]
    recall = float((nearest_distances(gt_band, pred_points) / diagonal < tau).mean())
    precision = (float((nearest_distances(pred_band, gt_points) / diagonal < tau).mean())
                 if len(pred_band) else 0.0)
    f = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return {"band_precision": precision, "band_recall": recall, "band_fscore": f}


class GroundTruth:
    """Per-object ground-truth samples and bounds of one dataset split, computed once and shared by folders."""

    def __init__(self, root: Path, category: str, split: str, config: GeometryConfig):
        self.records = {r.object_id: r for r in index_split(root, category, split, check_files=False).objects}
        self.config = config
        self._cache: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def get(self, object_id: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(points, lo, hi) of the object: its visible surface (or ``mesh.ply`` samples) and mesh bounds."""
        if object_id not in self._cache:
            rec = self.records[object_id]
            mesh = trimesh.load(rec.mesh_path, force="mesh")
            points = visible_surface_points(rec, self.config.n_points, self.config.depth_pixel_center)
            if points is None:
                points = sample_surface(mesh, self.config.n_points, self.config.seed)
            self._cache[object_id] = (points, np.asarray(mesh.bounds[0], np.float64),
                                      np.asarray(mesh.bounds[1], np.float64))
        return self._cache[object_id]


def folder_scores(folder: Path, truths: dict[tuple, GroundTruth], band: float, tau: float,
                  up_flag: str | None) -> dict[str, dict[str, float]]:
    """object id -> band scores of one eval folder."""
    summary, up_name = eval_summary(folder, up_flag)
    key = (summary["data_card"]["root"], summary["category"], summary["split"])
    if key not in truths:
        config = GeometryConfig(depth_pixel_center=float(summary.get("dataset_pixel_center") or 0.0))
        truths[key] = GroundTruth(Path(key[0]), key[1], key[2], config)
    truth = truths[key]
    with open(folder / "per_object.csv", newline="") as f:
        ids = [row["object_id"] for row in csv.DictReader(f)]
    out = {}
    for oid in ids:
        pred = eval_mesh(folder, oid)
        pred_points = (np.zeros((0, 3)) if is_empty_mesh(pred)
                       else sample_surface(pred, truth.config.n_points, truth.config.seed))
        points, lo, hi = truth.get(oid)
        try:
            out[oid] = band_scores(pred_points, points, lo, hi, AXES[up_name], band, tau)
        except ValueError as e:
            raise SystemExit(f"error: {folder}: {oid}: {e}") from None
    return out


def paired(base: dict[str, dict[str, float]], method: dict[str, dict[str, float]]) -> list[dict]:
    """Per metric: mean difference (method - baseline) over common objects, 95% t-interval, no-worse count."""
    ids = sorted(set(base) & set(method))
    rows = []
    for m in METRICS:
        a, b = np.array([base[i][m] for i in ids]), np.array([method[i][m] for i in ids])
        d = b - a
        _, _, half = t_interval(d.tolist())
        rows.append({"metric": m, "objects": len(ids), "baseline": float(a.mean()), "method": float(b.mean()),
                     "diff": float(d.mean()), "ci95": [float(d.mean() - half), float(d.mean() + half)],
                     "no_worse": int((d >= 0).sum())})
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--baseline", type=Path, required=True, help="eval folder of the reference method")
    ap.add_argument("--method", type=Path, nargs="+", required=True, help="eval folders to compare with it")
    ap.add_argument("--band", type=float, default=0.35, help="bottom share of the object's height scored")
    ap.add_argument("--tau", type=float, default=0.01, help="distance threshold, ground-truth diagonals")
    ap.add_argument("--up", choices=sorted(AXES), help="up axis of the objects (default: the dataset card's)")
    ap.add_argument("--json", type=Path, help="also write the per-object scores and the paired figures as JSON")
    args = ap.parse_args(argv)
    if not 0 < args.band <= 1 or not args.tau > 0:
        raise SystemExit(f"error: need 0 < --band <= 1 and --tau > 0, got {args.band}, {args.tau}")
    truths: dict[tuple, GroundTruth] = {}
    base = folder_scores(args.baseline, truths, args.band, args.tau, args.up)
    report = {"band": args.band, "tau": args.tau, "baseline": {"folder": str(args.baseline), "objects": base}}
    print(f"bottom {args.band:g} of the height, tau {args.tau:g} diagonals; paired against {args.baseline}\n")
    print("| method | metric | objects | baseline | method | difference (95% interval) | no worse |")
    print("|---|---|---:|---:|---:|---|---|")
    for folder in args.method:
        scores = folder_scores(folder, truths, args.band, args.tau, args.up)
        rows = paired(base, scores)
        report[str(folder)] = {"objects": scores, "paired": rows}
        for r in rows:
            print(f"| {folder.name} | {r['metric']} | {r['objects']} | {r['baseline']:.4f} | {r['method']:.4f} | "
                  f"{r['diff']:+.4f} [{r['ci95'][0]:+.4f}, {r['ci95'][1]:+.4f}] | {r['no_worse']}/{r['objects']} |")
    if args.json:
        args.json.write_text(json.dumps(report, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
