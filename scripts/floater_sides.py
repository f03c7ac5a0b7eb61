"""Where the floater surface lies: the floater fraction of eval folders split by the side of the object it leaves.

The floater fraction (``depthnerf.eval.geometry_metrics.floater_fraction``) counts the predicted surface outside
the ground-truth bounding box grown by a margin. This script splits that count by the box face each outside
sample leaves through (the axis of its largest excess over the grown box), named relative to the object and the
input camera:

- ``above`` / ``below``: the faces along the dataset's up axis;
- ``near`` / ``far``: of the four other faces, the one whose outward normal points most towards the input
  camera's centre (seen from the box centre, in the horizontal plane), and its opposite: ``near`` surface lies
  between the object and the camera that took the input photo, ``far`` surface behind the object;
- ``lateral``: the two remaining faces.

The five fractions of an object add up to its floater fraction (the same samples: ``GeometryConfig``'s point count
and seed, as ``depthnerf eval`` uses). Printed as the mean over objects per eval folder (a Markdown table).

    python scripts/floater_sides.py study/eval/cpu-cars-baseline study/eval/cpu-cars-depth [--up z] [--json OUT]

Needs ``depthnerf eval`` folders with meshes (``meshes/<object_id>.ply``, the eval's default) and the dataset
they were scored on (``summary.json``'s ``data_card.root``; each object's ``mesh.ply`` and input-view pose).
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np
import trimesh

from depthnerf.data.srn import index_split
from depthnerf.data.srn_format import read_pose
from depthnerf.eval.geometry_metrics import GeometryConfig, floater_box, is_empty_mesh, sample_surface

SIDES = ("near", "far", "above", "below", "lateral")
AXES = {"x": 0, "y": 1, "z": 2}


def classify_outside(points: np.ndarray, lo: np.ndarray, hi: np.ndarray, margin: float, up: int,
                     camera: np.ndarray) -> np.ndarray:
    """Side label index into :data:`SIDES` for every point, -1 for points inside ``[lo - margin, hi + margin]``.

    ``up``: index of the up axis (its sign is +: ``above`` is the face at ``hi[up]``). ``camera``: the input
    camera's centre in the same frame as the points. A point outside on several axes takes the axis of its
    largest excess; ``near`` is the horizontal face whose outward normal has the largest dot product with the
    direction from the box centre to the camera, with that direction's up component removed."""
    excess_lo = (lo - margin) - points          # > 0: outside through the face at lo on that axis
    excess_hi = points - (hi + margin)
    excess = np.maximum(excess_lo, excess_hi)
    outside = np.any(excess > 0, axis=-1)
    axis = np.argmax(excess, axis=-1)
    rows = np.arange(len(points))
    sign = np.where(excess_hi[rows, axis] > excess_lo[rows, axis], 1.0, -1.0)   # which face of that axis
    to_camera = camera - 0.5 * (lo + hi)
    to_camera[up] = 0.0
    # the four horizontal faces as (axis, sign); the near face maximises sign * to_camera[axis]
    faces = [(a, s) for a in range(3) if a != up for s in (1.0, -1.0)]
    near_axis, near_sign = max(faces, key=lambda f: f[1] * to_camera[f[0]])
    on_near_axis = axis == near_axis
    labels = np.full(len(points), SIDES.index("lateral"), dtype=np.int64)
    labels[on_near_axis & (sign == near_sign)] = SIDES.index("near")
    labels[on_near_axis & (sign != near_sign)] = SIDES.index("far")
    labels[(axis == up) & (sign > 0)] = SIDES.index("above")
    labels[(axis == up) & (sign < 0)] = SIDES.index("below")
    labels[~outside] = -1
    return labels


def side_fractions(pred: trimesh.Trimesh, gt: trimesh.Trimesh, camera: np.ndarray, up: int,
                   config: GeometryConfig | None = None,
                   pred_points: np.ndarray | None = None) -> dict[str, float]:
    """Fraction of ``pred``'s surface samples leaving ``gt``'s grown box through each side (all 0 when empty);
    ``config`` None = the eval's defaults; ``pred_points``: ``pred``'s surface samples, when already drawn (as for
    ``geometry_metrics.floater_fraction``)."""
    config = config or GeometryConfig()
    if is_empty_mesh(pred):
        return {s: 0.0 for s in SIDES}
    lo, hi, margin = floater_box(gt, config)
    points = sample_surface(pred, config.n_points, config.seed) if pred_points is None else pred_points
    labels = classify_outside(points, lo, hi, margin, up, camera)
    return {s: float((labels == k).mean()) for k, s in enumerate(SIDES)}


def card_up_axis(card: dict) -> str | None:
    """The up axis ("x", "y" or "z") a dataset card names under ``objects.up`` (sign dropped), None without one."""
    name = str(card.get("objects", {}).get("up", "")).lstrip("+")
    return name if name in AXES else None


def eval_summary(folder: Path, up_flag: str | None) -> tuple[dict, str]:
    """(``summary.json``, up axis name) of an eval folder: ``up_flag``, else the dataset card's (an error names
    the folder when neither says)."""
    summary_path = folder / "summary.json"
    if not summary_path.is_file():
        raise SystemExit(f"error: {summary_path}: missing (not a depthnerf eval folder)")
    summary = json.loads(summary_path.read_text())
    up_name = up_flag or card_up_axis(summary["data_card"].get("card") or {})
    if up_name is None:
        raise SystemExit(f"error: {folder}: the dataset card names no up axis; pass --up x|y|z")
    return summary, up_name


def eval_mesh(folder: Path, object_id: str) -> trimesh.Trimesh:
    """The mesh an eval extracted for one object (an error names the file when it is missing)."""
    mesh_path = folder / "meshes" / f"{object_id}.ply"
    if not mesh_path.is_file():
        raise SystemExit(f"error: {mesh_path}: missing (evaluate with meshes)")
    return trimesh.load(mesh_path, force="mesh")


def folder_sides(folder: Path, up_flag: str | None) -> tuple[str, list[dict[str, float]]]:
    """Per-object side fractions of one eval folder (and the up axis used)."""
    summary, up_name = eval_summary(folder, up_flag)
    root = Path(summary["data_card"]["root"])
    records = {r.object_id: r for r in index_split(root, summary["category"], summary["split"],
                                                   check_files=False).objects}
    with open(folder / "per_object.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    out = []
    for row in rows:
        oid = row["object_id"]
        rec = records[oid]
        camera = read_pose(rec.path / "pose" / f"{rec.view_names[int(row['input_view'])]}.txt")[:3, 3]
        pred = eval_mesh(folder, oid)
        gt = trimesh.load(rec.path / "mesh.ply", force="mesh")
        out.append({"object_id": oid, **side_fractions(pred, gt, np.asarray(camera, np.float64), AXES[up_name])})
    return up_name, out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folders", type=Path, nargs="+", help="depthnerf eval folders (with meshes)")
    ap.add_argument("--up", choices=sorted(AXES), help="up axis of the objects (default: the dataset card's)")
    ap.add_argument("--json", type=Path, help="also write the per-object fractions as JSON")
    args = ap.parse_args(argv)
    report = {}
    print("| eval | objects | floater fraction | " + " | ".join(SIDES) + " |")
    print("|---|---:|---:|" + "---:|" * len(SIDES))
    for folder in args.folders:
        up, rows = folder_sides(folder, args.up)
        report[str(folder)] = {"up": up, "objects": rows}
        means = {s: float(np.mean([r[s] for r in rows])) for s in SIDES}
        print(f"| {folder} | {len(rows)} | {sum(means.values()):.4f} | "
              + " | ".join(f"{means[s]:.4f}" for s in SIDES) + " |")
    if args.json:
        args.json.write_text(json.dumps(report, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
