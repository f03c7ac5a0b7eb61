"""How much of the object's colour each model's renders keep: chroma on the object, near and far from the input.

PSNR does not say whether a grey render of a red car is grey because it is blurred or because it lost the colour.
For each eval folder (``depthnerf eval --save-renders``) and every scored view, on the ground truth's object pixels
(any channel below ``--white``; the synthetic benchmark's background is white) this measures, in CIELAB
(``skimage.color.rgb2lab``):

* ``chroma``: the render's mean chroma ``sqrt(a^2 + b^2)`` there, beside the ground truth's (``gt_chroma``);
* ``delta_ab``: the mean distance between render and ground truth in the ``(a, b)`` plane (hue and saturation
  error, lightness left out).

Views are split by the angle between their optical axis and the input view's as ``scripts/angle_bins.py`` splits
them (a bin holds ``lo <= angle < hi``, the last one its upper edge too; views outside the edges are in no bin), each
object's views averaged per bin, then the objects.

    python scripts/colour_fidelity.py study/eval/cpu-cars-baseline study/eval/cars-none-sym [--bins 0 90 180]

``--baseline EVAL`` pairs each folder with that one per object (the objects both scored), as
``scripts/paired_difference.py`` does PSNR: per bin, the mean difference (folder - baseline) of ``delta_ab`` and of
the render's chroma with a 95% t-interval, and on how many objects the folder's ``delta_ab`` is lower.

    python scripts/colour_fidelity.py --baseline gl/eval/control gl/eval/global

A missing folder or file, or a folder scored on other views or another way than the ``--baseline`` (another
``--views-stride``, ``--resolution``, split, ``--ssim``, ``--scored`` or ``--input-views``:
``angle_bins.bin_pairing_refusal``), is one ``error:`` line, exit status 2.
"""

from __future__ import annotations

import argparse
import csv
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
from angle_bins import bin_index, bin_pairing_refusal, checked_edges, read_summary, view_angles
from paired_difference import t_interval
from skimage.color import rgb2lab

from depthnerf.data.srn_format import read_rgb
from depthnerf.errors import DepthnerfError


def unit_rgb(image: np.ndarray) -> np.ndarray:
    """An ``H x W x 3`` image as floats in [0, 1]: 8-bit values divided by 255, floats (``read_rgb``'s) as they are."""
    return image.astype(np.float64) / 255.0 if image.dtype == np.uint8 else image.astype(np.float64)


def view_colour(render: np.ndarray, gt: np.ndarray, white: float) -> tuple[float, float, float] | None:
    """(render chroma, ground-truth chroma, mean delta ab) on the ground truth's object pixels (any channel below
    ``white``, in [0, 1]); None: no object. 8-bit or [0, 1] float images alike (:func:`unit_rgb`)."""
    render, gt = unit_rgb(render), unit_rgb(gt)
    mask = (gt < white).any(-1)
    if not mask.any():
        return None
    lab_r, lab_g = rgb2lab(render[mask][None]), rgb2lab(gt[mask][None])
    chroma_r = np.hypot(lab_r[..., 1], lab_r[..., 2]).mean()
    chroma_g = np.hypot(lab_g[..., 1], lab_g[..., 2]).mean()
    delta_ab = np.hypot(lab_r[..., 1] - lab_g[..., 1], lab_r[..., 2] - lab_g[..., 2]).mean()
    return float(chroma_r), float(chroma_g), float(delta_ab)


def object_colour(folder: Path, bins: list[float], white: float) -> dict[str, dict[str, np.ndarray]]:
    """Bin label -> object id -> the mean over its views in that bin of (chroma, gt_chroma, delta_ab); ``bins``:
    the edges, in any order (:func:`angle_bins.bin_index`)."""
    edges = sorted(bins)
    angles = view_angles(folder)
    per_object: dict[str, dict[str, list[tuple[float, float, float]]]] = defaultdict(lambda: defaultdict(list))
    with open(folder / "renders.csv", newline="") as f:
        for row in csv.DictReader(f):
            k = bin_index(angles[(row["object_id"], int(row["view"]))], edges)
            if k is None:
                continue
            label = f"{edges[k]:g}-{edges[k + 1]:g}"
            gt_path = Path(row["gt_path"])
            gt = read_rgb(gt_path if gt_path.is_absolute() else folder / gt_path)
            got = view_colour(read_rgb(folder / row["render_path"]), gt, white)
            if got is not None:
                per_object[label][row["object_id"]].append(got)
    return {label: {key: np.mean(views, axis=0) for key, views in objects.items()}
            for label, objects in per_object.items()}


def folder_colour(folder: Path, bins: list[float], white: float) -> dict[str, tuple[float, float, float, int]]:
    """Bin label -> (chroma, gt_chroma, delta_ab, objects), object means of view means."""
    out = {}
    for label, objects in object_colour(folder, bins, white).items():
        means = np.array(list(objects.values()))
        out[label] = (*means.mean(axis=0), len(means))
    return out


def paired_colour(baseline: dict[str, dict[str, np.ndarray]], method: dict[str, dict[str, np.ndarray]]
                  ) -> dict[str, dict[str, float]]:
    """Per bin both have, over the objects both scored there: the mean ``delta_ab`` and chroma of each, the mean
    differences (method - baseline) with their 95% half-widths, and the objects whose ``delta_ab`` is lower."""
    out = {}
    for label in sorted(set(baseline) & set(method), key=lambda s: float(s.split("-")[0])):
        keys = sorted(set(baseline[label]) & set(method[label]))
        if not keys:
            continue
        base = np.array([baseline[label][k] for k in keys])
        other = np.array([method[label][k] for k in keys])
        delta, _, delta_hw = t_interval(list(other[:, 2] - base[:, 2]))
        chroma, _, chroma_hw = t_interval(list(other[:, 0] - base[:, 0]))
        out[label] = {"objects": len(keys), "delta_ab_baseline": float(base[:, 2].mean()),
                      "delta_ab_method": float(other[:, 2].mean()), "delta_ab_diff": delta,
                      "delta_ab_hw": delta_hw, "chroma_diff": chroma, "chroma_hw": chroma_hw,
                      "lower": int((other[:, 2] < base[:, 2]).sum())}
    return out


def interval(mean: float, half_width: float) -> str:
    """``+m [+lo, +hi]``: a mean difference and its 95% interval."""
    return f"{mean:+.2f} [{mean - half_width:+.2f}, {mean + half_width:+.2f}]"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("evals", nargs="+", type=Path, help="eval folders (depthnerf eval --save-renders)")
    p.add_argument("--bins", type=float, nargs="+", default=[0, 90, 180], help="bin edges, degrees")
    p.add_argument("--white", type=float, default=0.95, help="ground-truth object pixels: any channel below this")
    p.add_argument("--baseline", type=Path, help="pair each eval folder with this one per object")
    args = p.parse_args(argv)
    try:
        return _run(args)
    except DepthnerfError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2


def _run(args: argparse.Namespace) -> int:
    edges = checked_edges(args.bins)
    if args.baseline is not None:
        for folder in args.evals:
            refusal = bin_pairing_refusal(args.baseline, read_summary(args.baseline), folder, read_summary(folder))
            if refusal is not None:
                raise DepthnerfError(refusal)
        base = object_colour(args.baseline, edges, args.white)
        print(f"paired against {args.baseline.name}: method - baseline, 95% interval")
        print("| eval | bin (deg) | objects | delta ab | difference | chroma difference | lower delta ab |")
        print("|---|---|---:|---|---|---|---:|")
        for folder in args.evals:
            for label, r in paired_colour(base, object_colour(folder, edges, args.white)).items():
                delta = interval(r["delta_ab_diff"], r["delta_ab_hw"])
                chroma = interval(r["chroma_diff"], r["chroma_hw"])
                print(f"| {folder.name} | {label} | {r['objects']} | {r['delta_ab_baseline']:.2f} -> "
                      f"{r['delta_ab_method']:.2f} | {delta} | {chroma} | {r['lower']}/{r['objects']} |")
        return 0
    print("| eval | bin (deg) | objects | render chroma | ground-truth chroma | mean delta ab |")
    print("|---|---|---:|---:|---:|---:|")
    for folder in args.evals:
        result = folder_colour(folder, edges, args.white)
        for label in sorted(result, key=lambda s: float(s.split("-")[0])):
            chroma, gt_chroma, delta, n = result[label]
            print(f"| {folder.name} | {label} | {n} | {chroma:.2f} | {gt_chroma:.2f} | {delta:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
