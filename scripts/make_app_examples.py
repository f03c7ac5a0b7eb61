"""Write the bundled example photos of ``depthnerf app`` (``depthnerf/app/examples/``) with ``depthnerf synth``.

Objects: test object 0 of ``depthnerf synth --category C --seed 2718 --test-objects 1 --framing F`` (the seed
of ``depthnerf demo``; the shipped checkpoints were trained on seed 0, so these objects were never seen; F is the
framing of the shipped ``cpu-C-depth`` checkpoint's training data, read from its card), test view 64 (about 23 degrees elevation, as the demo's input
view), 128 px. The car is saved as an RGBA cut-out (alpha =
the synthetic object mask), the chair as RGB on white, so the page shows both background-removal paths (alpha and
border colour). Every pixel is synthesised by this package: no third-party images.

    python scripts/make_app_examples.py            # rewrites depthnerf/app/examples/{car_rgba,chair_white}.png
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image

from depthnerf.pretrained.load import load_pretrained

SEED = 2718
VIEW = 64
EXAMPLES = {"cars": "car_rgba.png", "chairs": "chair_white.png"}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "depthnerf/app/examples")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        for category, name in EXAMPLES.items():
            framing = load_pretrained(f"cpu-{category}-depth").spec.framing
            subprocess.run([sys.executable, "-m", "depthnerf", "synth", "--category", category, "--out", tmp,
                            "--train-objects", "0", "--val-objects", "0", "--test-objects", "1", "--seed",
                            str(SEED), "--framing", framing, "--quiet"], check=True)
            obj = Path(tmp) / f"{category}_test" / f"synth_{category}_test_000000"
            rgb = np.asarray(Image.open(obj / "rgb" / f"{VIEW:06d}.png").convert("RGB"))
            mask = np.asarray(Image.open(obj / "mask" / f"{VIEW:06d}.png").convert("L"))
            if name.endswith("_rgba.png"):
                Image.fromarray(np.dstack([rgb, mask]), "RGBA").save(args.out / name, optimize=True)
            else:
                Image.fromarray(rgb, "RGB").save(args.out / name, optimize=True)
            print(f"wrote {args.out / name} ({framing} framing)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
