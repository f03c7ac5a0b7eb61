"""How much of the object's colour each model's renders keep: chroma on the object, near and far from the input.

PSNR does not say whether a grey render of a red car is grey because it is blurred or because it lost the colour.
For each eval folder (``depthnerf eval --save-renders``) and every scored view, on the ground truth's object pixels
(any channel below ``--white``; the synthetic benchmark's background is white) this measures, in CIELAB
(``skimage.color.rgb2lab``):

* ``chroma``: the render's mean chroma ``sqrt(a^2 + b^2)`` there, beside the ground truth's (``gt_chroma``);
* ``delta_ab``: the mean distance between render and ground truth in the ``(a, b)`` plane (hue and saturation
  error, lightness left out).

Views are split by the angle between their optical axis and the input view's (``scripts/angle_bins.py``), each
object's views averaged per bin, then the objects.

    python scripts/colour_fidelity.py study/eval/cpu-cars-baseline study/eval/cars-none-sym [--bins 0 90 180]
"""

from __future__ import annotations

import argparse
import csv
from collections import defaultdict
from pathlib import Path

import numpy as np
from angle_bins import view_angles
from skimage.color import rgb2lab

from depthnerf.data.srn_format import read_rgb


def view_colour(render: np.ndarray, gt: np.ndarray, white: float) -> tuple[float, float, float] | None:
    """(render chroma, ground-truth chroma, mean delta ab) on the ground truth's object pixels; None: no object."""
    mask = (gt < white * 255).any(-1)
    if not mask.any():
        return None
    lab_r, lab_g = rgb2lab(render[mask][None]), rgb2lab(gt[mask][None])
    chroma_r = np.hypot(lab_r[..., 1], lab_r[..., 2]).mean()
    chroma_g = np.hypot(lab_g[..., 1], lab_g[..., 2]).mean()
    delta_ab = np.hypot(lab_r[..., 1] - lab_g[..., 1], lab_r[..., 2] - lab_g[..., 2]).mean()
    return float(chroma_r), float(chroma_g), float(delta_ab)


def folder_colour(folder: Path, bins: list[float], white: float) -> dict[str, tuple[float, float, float, int]]:
    """Bin label -> (chroma, gt_chroma, delta_ab, objects), object means of view means."""
    angles = view_angles(folder)
    per_object: dict[str, dict[str, list[tuple[float, float, float]]]] = defaultdict(lambda: defaultdict(list))
    with open(folder / "renders.csv", newline="") as f:
        for row in csv.DictReader(f):
            key = (row["object_id"], int(row["view"]))
            angle = angles[key]
            label = next(f"{lo:g}-{hi:g}" for lo, hi in zip(bins, bins[1:], strict=False) if angle <= hi)
            gt_path = Path(row["gt_path"])
            gt = read_rgb(gt_path if gt_path.is_absolute() else folder / gt_path)
            got = view_colour(read_rgb(folder / row["render_path"]), gt, white)
            if got is not None:
                per_object[label][row["object_id"]].append(got)
    out = {}
    for label, objects in per_object.items():
        means = np.array([np.mean(v, axis=0) for v in objects.values()])
        out[label] = (*means.mean(axis=0), len(means))
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("evals", nargs="+", type=Path, help="eval folders (depthnerf eval --save-renders)")
    p.add_argument("--bins", type=float, nargs="+", default=[0, 90, 180], help="bin edges, degrees")
    p.add_argument("--white", type=float, default=0.95, help="ground-truth object pixels: any channel below this")
    args = p.parse_args()
    print("| eval | bin (deg) | objects | render chroma | ground-truth chroma | mean delta ab |")
    print("|---|---|---:|---:|---:|---:|")
    for folder in args.evals:
        result = folder_colour(folder, args.bins, args.white)
        for label in sorted(result, key=lambda s: float(s.split("-")[0])):
            chroma, gt_chroma, delta, n = result[label]
            print(f"| {folder.name} | {label} | {n} | {chroma:.2f} | {gt_chroma:.2f} | {delta:.2f} |")


if __name__ == "__main__":
    main()
