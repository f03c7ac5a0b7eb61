"""Look at meshes: each ``mesh.ply`` (a reconstruct folder or a file) drawn from three directions in one PNG.

Vertex colours as the network gave them, on a blue-grey backdrop so that white density shows; axes in world
units (+z up). Needs matplotlib (``pip install -e ".[figures]"``).

    python scripts/render_meshes.py OUT_A OUT_B --labels before after --out docs/figures/meshes.png
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import trimesh

VIEWS = ((20, 30), (20, 150), (60, 90))
"""(elevation, azimuth) in degrees of the three panels of each row."""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("paths", nargs="+", type=Path, help="reconstruct folders or .ply meshes")
    ap.add_argument("--labels", nargs="+", help="row labels (default: the paths)")
    ap.add_argument("--max-faces", type=int, default=8000, help="faces drawn per mesh (evenly thinned)")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    labels = args.labels or [str(p) for p in args.paths]
    if len(labels) != len(args.paths):
        print("error: --labels: give one label per path", file=sys.stderr)
        return 2
    fig = plt.figure(figsize=(4 * len(VIEWS), 3.6 * len(args.paths)))
    for row, (path, label) in enumerate(zip(args.paths, labels, strict=True)):
        file = path / "mesh.ply" if path.is_dir() else path
        if not file.is_file():
            print(f"error: {file}: no mesh", file=sys.stderr)
            return 2
        mesh = trimesh.load(file, process=False, force="mesh")
        if len(mesh.faces) == 0:
            print(f"error: {file}: empty mesh (no faces)", file=sys.stderr)
            return 2
        faces = mesh.faces[:: max(1, len(mesh.faces) // args.max_faces)]
        colors = np.asarray(mesh.visual.vertex_colors)[faces[:, 0], :3] / 255.0
        lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
        center, radius = (lo + hi) / 2, float((hi - lo).max()) / 2
        for k, (elev, azim) in enumerate(VIEWS):
            ax = fig.add_subplot(len(args.paths), len(VIEWS), row * len(VIEWS) + k + 1, projection="3d")
            ax.add_collection3d(Poly3DCollection(mesh.vertices[faces], facecolors=colors, edgecolor="none"))
            for axis, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), center, strict=True):
                axis(c - radius, c + radius)
            ax.view_init(elev, azim)
            ax.set_facecolor((0.62, 0.70, 0.80))
            ax.set_title(f"{label} (elevation {elev}, azimuth {azim})", fontsize=9)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=70)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
