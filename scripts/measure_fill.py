"""Measure the training fill of the synthetic benchmark (``depthnerf.data.synth.framing.Framing.fill``).

Fill = the fraction of the frame the object's longer mask bounding-box side takes. Protocol: the median over the
masks of every view of ``--objects`` train objects per category (50 views each) at ``--resolution`` px, seed 0,
for each framing. Prints one line per (framing, category) and the table ``Framing.fill`` holds.

    python scripts/measure_fill.py                     # 6 objects x 50 views per category, 128 px (~2 min)
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

from depthnerf.data.srn import mask_bboxes
from depthnerf.data.srn_format import read_mask
from depthnerf.data.synth.framing import FRAMINGS


def mask_fills(paths: list[Path]) -> np.ndarray:
    """Longer side of each non-empty mask's bounding box over the image side."""
    masks = [m for m in (read_mask(p) for p in paths) if m.any()]
    boxes = mask_bboxes(torch.from_numpy(np.stack(masks))).numpy()  # [x0, y0, x1, y1], inclusive
    sides = np.maximum(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]) + 1
    return sides / masks[0].shape[0]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--objects", type=int, default=6, help="train objects per category (default 6)")
    parser.add_argument("--resolution", type=int, default=128, help="image size (default 128)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        for framing in FRAMINGS:
            for category in ("cars", "chairs"):
                root = Path(tmp) / framing
                subprocess.run([sys.executable, "-m", "depthnerf", "synth", "--category", category, "--out", str(root),
                                "--train-objects", str(args.objects), "--val-objects", "0", "--test-objects", "0",
                                "--resolution", str(args.resolution), "--framing", framing, "--quiet"], check=True)
                fills = mask_fills(sorted((root / f"{category}_train").glob("*/mask/*.png")))
                table = FRAMINGS[framing].fill(category, float("nan"))  # nan: not measured yet
                print(f"{framing:7s} {category:7s} median fill {np.median(fills):.3f} over {len(fills)} masks "
                      f"(10th-90th percentile {np.percentile(fills, 10):.3f}-{np.percentile(fills, 90):.3f}); "
                      f"Framing.fill: {table}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
