"""Connected pieces of the eval meshes and the colour the network gives them (docs/RESULTS.md, "Cars, geometry").

For the first N test objects of each run: loads ``EVAL_DIR/meshes/<object>.ply`` (written by ``depthnerf eval
--save-renders``), splits it into connected components, and queries the run's fine network colour at each
component's vertices (viewed from the input camera, as the mesh is extracted). Prints, per object, the number of
components and for the largest four: vertex count, centroid (world) and mean RGB.

    python scripts/mesh_components.py --data study/data --objects 3 study/runs/cars-bundled study/runs/cars-none
(the eval folder of ``study/runs/X`` is taken as ``study/eval/X``; ``--eval-root`` changes that).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
import trimesh

from depthnerf.data.srn import index_split
from depthnerf.eval.objects import prepare_object, protocol_views
from depthnerf.infer.session import InferenceSession, SessionOptions
from depthnerf.pretrained.load import load_pretrained
from depthnerf.render.mesh import field_queries


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path, help="run folders")
    parser.add_argument("--data", type=Path, required=True, help="dataset root")
    parser.add_argument("--eval-root", type=Path, help="folder holding <run name>/meshes (default: RUN/../../eval)")
    parser.add_argument("--objects", type=int, default=3, help="first N test objects")
    args = parser.parse_args(argv)
    torch.set_grad_enabled(False)
    for run in args.runs:
        pre = load_pretrained(run)
        ev = (args.eval_root or run.resolve().parent.parent / "eval") / run.name
        records = index_split(args.data, pre.spec.category, "test").objects[: args.objects]
        session = InferenceSession(pre, SessionOptions(inputs="dataset", data_root=args.data, records=records))
        for rec in records:
            mesh_path = ev / "meshes" / f"{rec.object_id}.ply"
            if not mesh_path.is_file():
                print(f"error: {mesh_path}: missing (run depthnerf eval --save-renders)", file=sys.stderr)
                return 2
            obj = prepare_object(session, rec, protocol_views(rec.num_views, 25))
            _, color_fn = field_queries(pre.model, obj.encoded.enc, obj.source.poses[0, :3, 3])
            mesh = trimesh.load(mesh_path, force="mesh")  # an empty eval mesh loads as an empty Trimesh
            parts = sorted(mesh.split(only_watertight=False), key=lambda m: -len(m.vertices))
            cells = []
            for part in parts[:4]:
                rgb = color_fn(torch.as_tensor(part.vertices, dtype=torch.float32)).numpy().mean(0)
                cells.append(f"{len(part.vertices)} verts at {np.round(part.vertices.mean(0), 2).tolist()} "
                             f"rgb {[round(float(c), 2) for c in rgb]}")
            print(f"{run.name} {rec.object_id}: {len(parts)} components; " + "; ".join(cells))
    return 0


if __name__ == "__main__":
    sys.exit(main())
