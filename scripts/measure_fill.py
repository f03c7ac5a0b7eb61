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
from PIL import Image

from depthnerf.data.synth.framing import FRAMINGS


def mask_fill(path: Path) -> float | None:
    """Longer side of the mask's bounding box over the image side (None for an empty mask)."""
    m = np.asarray(Image.open(path).convert("L")) > 0
    ys, xs = np.nonzero(m)
    if ys.size == 0:
        return None
    return max(ys.max() - ys.min() + 1, xs.max() - xs.min() + 1) / m.shape[0]


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
                fills = [f for p in sorted((root / f"{category}_train").glob("*/mask/*.png"))
                         if (f := mask_fill(p)) is not None]
                table = FRAMINGS[framing].fill(category)
                print(f"{framing:7s} {category:7s} median fill {np.median(fills):.3f} over {len(fills)} masks "
                      f"(10th-90th percentile {np.percentile(fills, 10):.3f}-{np.percentile(fills, 90):.3f}); "
                      f"Framing.fill: {table}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
