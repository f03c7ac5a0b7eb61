"""Tile one view of every object of a generated (or real SRN) split into a contact sheet PNG.

    python scripts/synth_contact_sheet.py data/synth/cars_test --view 64 --out cars_test_v64.png
    python scripts/synth_contact_sheet.py data/synth/cars_train --view 0 --depth --out sheet.png

``--depth`` adds the depth map (normalised per image, background black) under each RGB tile.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
from PIL import Image

from depthnerf.data import srn_format


def tile(split_dir: Path, view: int, with_depth: bool, columns: int, limit: int) -> np.ndarray:
    objects = sorted(p for p in split_dir.iterdir() if (p / "rgb").is_dir())[:limit]
    if not objects:
        raise SystemExit(f"{split_dir}: no object folders with rgb/")
    tiles = []
    for obj in objects:
        rgbs = sorted((obj / "rgb").glob("*.png"))
        rgb = srn_format.read_rgb(rgbs[min(view, len(rgbs) - 1)])
        if with_depth:
            depth_path = obj / "depth" / (rgbs[min(view, len(rgbs) - 1)].stem + ".npz")
            depth = srn_format.read_depth(depth_path, allow_empty=True) if depth_path.exists() else np.zeros(rgb.shape[:2])
            vis = np.zeros_like(depth)
            if (depth > 0).any():
                lo, hi = depth[depth > 0].min(), depth[depth > 0].max()
                vis = np.where(depth > 0, 1.0 - 0.8 * (depth - lo) / max(hi - lo, 1e-6), 0.0)
            rgb = np.concatenate([rgb, np.repeat(vis[..., None], 3, axis=-1)], axis=0)
        tiles.append(rgb)
    h, w = tiles[0].shape[:2]
    rows = math.ceil(len(tiles) / columns)
    sheet = np.ones((rows * h, columns * w, 3), dtype=np.float32)
    for k, t in enumerate(tiles):
        r, c = divmod(k, columns)
        sheet[r * h:(r + 1) * h, c * w:(c + 1) * w] = t
    return sheet


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("split_dir", type=Path, help="e.g. data/synth/cars_test")
    parser.add_argument("--view", type=int, default=64, help="view index (default 64, the SRN input view)")
    parser.add_argument("--depth", action="store_true", help="add depth tiles")
    parser.add_argument("--columns", type=int, default=8)
    parser.add_argument("--limit", type=int, default=64, help="at most this many objects")
    parser.add_argument("--out", type=Path, default=Path("contact_sheet.png"))
    args = parser.parse_args()
    sheet = tile(args.split_dir, args.view, args.depth, args.columns, args.limit)
    Image.fromarray(np.round(sheet * 255).astype(np.uint8)).save(args.out)
    print(f"wrote {args.out} ({sheet.shape[1]}x{sheet.shape[0]})")


if __name__ == "__main__":
    main()
