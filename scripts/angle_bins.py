"""PSNR / SSIM binned by the angle between each target view and the input view, paired per object.

The far side of an object (targets 135-180 degrees from the input camera) is where a single-image model guesses;
an overall mean hides it. For each eval folder (``depthnerf eval --save-renders``: its ``renders.csv`` holds the
per-view scores) this reads the dataset's camera poses, puts every scored view in a bin by the angle between its
optical axis and the input view's, averages each object's views per bin, and compares every ``--method`` with
the ``--baseline`` on the objects both scored in that bin: mean difference, 95% t-interval and wins. A bin holds the
views with ``lo <= angle < hi`` (the last one its upper edge too); views outside the edges are in no bin.

    python scripts/angle_bins.py --baseline study/eval/cars-bundled --method study/eval/cars-bundled-sym \
        [--bins 0 45 90 135 180] [--json OUT.json]

A folder whose ``renders.csv`` is not the one its ``summary.json`` was written with (an earlier evaluation's, left
behind) is refused; so is a ``--method`` evaluation scored on other views or another way than the baseline (another
``--views-stride``, ``--resolution``, split, ``--ssim`` or ``--scored``: ``paired_difference.pairing_refusal``) or
conditioned on other ``--input-views``, and a missing folder or file: one ``error:`` line, exit status 2.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
from paired_difference import pairing_refusal, t_interval

from depthnerf.data.protocol import protocol_views
from depthnerf.data.srn import ObjectRecord, index_split
from depthnerf.data.srn_format import read_pose
from depthnerf.errors import DepthnerfError

METRICS = ("psnr", "ssim")
PER_OBJECT = ("object_id", "input_view")
"""Columns of ``per_object.csv`` read here."""
RENDERS = ("object_id", "view", *METRICS)
"""Columns of ``renders.csv`` read here."""


def _read_csv(path: Path, columns: tuple[str, ...], numbers: tuple[str, ...] = ()) -> list[dict[str, str]]:
    """The rows of ``path``; a one-line error when it is missing or unreadable, lacks one of ``columns``, or has a
    cell of ``numbers`` that is not a finite number (a whole one in the view columns)."""
    if not path.is_file():
        raise DepthnerfError(f"{path}: missing (run depthnerf eval with --save-renders --out {path.parent})")
    try:
        with open(path, newline="", encoding="utf-8") as f:
            reader = csv.DictReader(f)
            rows, header = list(reader), reader.fieldnames or []
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise DepthnerfError(f"{path}: unreadable ({err})") from None
    missing = [c for c in columns if c not in header]
    if missing:
        raise DepthnerfError(f"{path}: no {', '.join(missing)} column (not the file depthnerf eval writes)")
    for line, row in enumerate(rows, start=2):
        for column in numbers:
            try:
                ok = math.isfinite(int(row[column]) if column.endswith("view") else float(row[column]))
            except (TypeError, ValueError):
                ok = False
            if not ok:
                raise DepthnerfError(f"{path}: line {line}: {column} {row[column]!r} is not a finite number")
    return rows


def read_summary(folder: Path) -> dict:
    """``folder/summary.json`` (a one-line error when the folder or the file is missing or unreadable)."""
    path = folder / "summary.json"
    if not folder.is_dir():
        raise DepthnerfError(f"{folder}: no such eval folder (run depthnerf eval --save-renders --out {folder})")
    if not path.is_file():
        raise DepthnerfError(f"{path}: missing (run depthnerf eval --save-renders --out {folder})")
    try:
        summary = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise DepthnerfError(f"{path}: unreadable ({err})") from None
    if not isinstance(summary, dict) or not isinstance(summary.get("data_card"), dict):
        raise DepthnerfError(f"{path}: not an eval summary (no data_card)")
    return summary


def read_renders(folder: Path, summary: dict, records: dict[str, ObjectRecord]) -> list[dict[str, str]]:
    """The rows of ``folder/renders.csv``, refused (one line) unless they are the views the summary's evaluation
    scored: the summary names ``renders.csv`` (written with ``--save-renders``), and the file lists exactly the
    objects of ``per_object.csv`` with each object's protocol targets at the summary's ``views_stride`` (and its
    ``input_views``, when every object had the same). A renders.csv an earlier evaluation left behind fails this."""
    path = folder / "renders.csv"
    redo = f"re-run depthnerf eval --save-renders --overwrite --out {folder}"
    if summary.get("renders_csv") != path.name:
        raise DepthnerfError(f"{path}: not written by the evaluation of {folder / 'summary.json'} (it records no "
                             f"renders.csv: evaluated without --save-renders); {redo}")
    stride = summary.get("views_stride", 1)
    inputs = summary.get("input_views")  # the same views for every object: a list of view indices
    inputs = inputs if isinstance(inputs, list) and inputs and isinstance(inputs[0], int) else None
    objects = [row["object_id"] for row in _read_csv(folder / "per_object.csv", PER_OBJECT, ("input_view",))]
    rows = _read_csv(path, RENDERS, ("view", *METRICS))
    views: dict[str, list[int]] = defaultdict(list)
    for row in rows:
        views[row["object_id"]].append(int(row["view"]))
    if sorted(views) != sorted(objects):
        raise DepthnerfError(f"{path}: lists {len(views)} objects, {folder / 'per_object.csv'} {len(objects)} "
                             f"(other objects): a renders.csv of another evaluation; {redo}")
    for oid in objects:
        if oid not in records:
            raise DepthnerfError(f"{folder / 'summary.json'}: object {oid} is not in the dataset it names "
                                 f"({summary['data_card'].get('root')})")
        try:
            expected = protocol_views(records[oid].num_views, stride, inputs).targets
        except DepthnerfError as err:
            raise DepthnerfError(f"{folder / 'summary.json'}: object {oid}: {err}") from None
        if tuple(sorted(views[oid])) != expected:
            chosen = f" and input views {' '.join(map(str, inputs))}" if inputs else ""
            raise DepthnerfError(f"{path}: object {oid} has views {sorted(views[oid])[:4]}..., not the "
                                 f"{len(expected)} targets of views_stride {stride}{chosen} that summary.json "
                                 f"records: a renders.csv of another evaluation; {redo}")
    return rows


def bin_pairing_refusal(baseline: Path, base: dict, method: Path, other: dict) -> str | None:
    """One line refusing to pair, bin by bin, the evaluation in ``method`` (its ``summary.json`` mapping ``other``)
    with the one in ``baseline`` (``base``): scored differently (``paired_difference.pairing_refusal``) or
    conditioned on other input views (``input_views``; a summary that does not record them is not compared), which
    puts other views in each bin; None when they pair."""
    refusal = pairing_refusal(baseline, base, method, other)
    if refusal is not None:
        return refusal
    views = [s.get("input_views") for s in (base, other)]
    if None in views or views[0] == views[1]:
        return None
    named = [" ".join(map(str, v)) if isinstance(v, list) else str(v) for v in views]
    return (f"{method / 'summary.json'} was scored with --input-views {named[1]} but {baseline / 'summary.json'} "
            f"with --input-views {named[0]}: other views in each bin, so not paired (paired_difference.py "
            "--common-views pairs the views both scored)")


def optical_axis(record: ObjectRecord, view: int) -> np.ndarray:
    """The unit optical axis (the camera's +z in the world) of view ``view`` of ``record``, from its pose file."""
    z = read_pose(record.pose_path(view))[:3, 2]
    return z / np.linalg.norm(z)


def axis_angle(a: np.ndarray, b: np.ndarray) -> float:
    """Degrees between two unit axes."""
    return math.degrees(math.acos(max(-1.0, min(1.0, float(np.dot(a, b))))))


def view_angles(folder: Path) -> dict[tuple[str, int], float]:
    """(object id, view) -> degrees between the view's optical axis and its object's input view's."""
    summary = read_summary(folder)
    root = Path(summary["data_card"]["root"])
    records = {r.object_id: r for r in index_split(root, summary["category"], summary["split"],
                                                   check_files=False).objects}
    inputs = {row["object_id"]: int(row["input_view"])
              for row in _read_csv(folder / "per_object.csv", PER_OBJECT, ("input_view",))}
    rows = read_renders(folder, summary, records)
    input_axes = {oid: optical_axis(records[oid], view) for oid, view in inputs.items()}
    return {(row["object_id"], int(row["view"])): axis_angle(input_axes[row["object_id"]],
                                                             optical_axis(records[row["object_id"]], int(row["view"])))
            for row in rows}


def bin_index(angle: float, edges: list[float]) -> int | None:
    """The bin ``k`` with ``edges[k] <= angle < edges[k + 1]`` (the last bin includes its upper edge), None for an
    angle outside the edges."""
    if not edges[0] <= angle <= edges[-1]:
        return None
    return min(int(np.searchsorted(edges, angle, side="right")) - 1, len(edges) - 2)


def binned(folder: Path, edges: list[float], angles: dict[tuple[str, int], float]) -> dict[int, dict[str, dict]]:
    """bin -> object id -> {metric: mean over the object's views in the bin, "views": count}."""
    acc: dict[int, dict[str, dict[str, list[float]]]] = defaultdict(lambda: defaultdict(lambda: defaultdict(list)))
    for row in _read_csv(folder / "renders.csv", RENDERS, ("view", *METRICS)):
        k = bin_index(angles[(row["object_id"], int(row["view"]))], edges)
        if k is None:
            continue
        for m in METRICS:
            acc[k][row["object_id"]][m].append(float(row[m]))
    return {k: {oid: {**{m: float(np.mean(v[m])) for m in METRICS}, "views": len(v["psnr"])}
                for oid, v in objs.items()} for k, objs in acc.items()}


def compare(base: dict, method: dict, edges: list[float]) -> list[dict]:
    """Per bin and metric: paired mean difference (method - baseline), 95% t-interval, wins."""
    out = []
    for k in range(len(edges) - 1):
        ids = sorted(set(base.get(k, {})) & set(method.get(k, {})))
        for m in METRICS:
            if not ids:
                continue
            a = np.array([base[k][i][m] for i in ids])
            b = np.array([method[k][i][m] for i in ids])
            d = b - a
            _, _, half = t_interval(d.tolist())
            out.append({"bin": f"{edges[k]:g}-{edges[k + 1]:g}", "metric": m, "objects": len(ids),
                        "views": int(sum(method[k][i]["views"] for i in ids)), "baseline": float(a.mean()),
                        "method": float(b.mean()), "diff": float(d.mean()), "ci95": [d.mean() - half, d.mean() + half],
                        "wins": int((d > 0).sum())})
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--baseline", type=Path, required=True, help="eval folder of the reference method")
    ap.add_argument("--method", type=Path, nargs="+", required=True, help="eval folders to compare with it")
    ap.add_argument("--bins", type=float, nargs="+", default=[0, 45, 90, 135, 180], help="bin edges, degrees")
    ap.add_argument("--json", type=Path, help="also write the figures as JSON")
    args = ap.parse_args(argv)
    try:
        return _run(args)
    except DepthnerfError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2


def checked_edges(bins: list[float]) -> list[float]:
    """``--bins`` sorted; a one-line error unless there are at least two edges within 0..180 degrees."""
    edges = sorted(bins)
    if len(edges) < 2 or edges[0] < 0 or edges[-1] > 180:
        raise DepthnerfError("--bins needs >= 2 edges within 0..180")
    return edges


def _run(args: argparse.Namespace) -> int:
    edges = checked_edges(args.bins)
    angles = view_angles(args.baseline)
    base = binned(args.baseline, edges, angles)
    base_summary = read_summary(args.baseline)
    report = {}
    for folder in args.method:
        method_angles = view_angles(folder)
        refusal = bin_pairing_refusal(args.baseline, base_summary, folder, read_summary(folder))
        if refusal is not None:
            raise DepthnerfError(refusal)
        rows = compare(base, binned(folder, edges, method_angles), edges)
        report[str(folder)] = rows
        print(f"\n{folder} - {args.baseline} (paired per object; objects and views per bin)\n")
        print("| bin (deg) | metric | objects | views | baseline | method | difference (95% CI) | wins |")
        print("|---|---|---|---|---|---|---|---|")
        for r in rows:
            fmt = ".2f" if r["metric"] == "psnr" else ".4f"
            print(f"| {r['bin']} | {r['metric']} | {r['objects']} | {r['views']} | {r['baseline']:{fmt}} | "
                  f"{r['method']:{fmt}} | {r['diff']:+{fmt}} [{r['ci95'][0]:+{fmt}}, {r['ci95'][1]:+{fmt}}] | "
                  f"{r['wins']}/{r['objects']} |")
    if args.json:
        args.json.write_text(json.dumps(report, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
