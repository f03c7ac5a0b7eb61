"""Is a reconstruction's mesh one clean object? Its pieces, the ones the photo shows, and stray faces above it.

For each ``depthnerf reconstruct`` output folder (``mesh.ply``: world frame, +z up; ``depths.npz``: view 0 is the
input camera; ``input_mask.png``) prints: ``components`` (connected pieces), ``main_share`` (fraction of all faces
in the largest piece), ``seen_pieces`` and ``object_share`` (the detached pieces the photo shows, and the fraction
of all faces in the main piece or one of them; a piece is shown by the photo when at least ``--min-seen`` of its
faces, default 0.25, are both visible from the input camera, no other face nearer along the ray to their centroid,
and on the input's mask: a chair's runner cut off from the seat by a lost strut is such a piece, a slab hidden
behind the object or beside its silhouette is not; a closed piece seen from one side shows about half its faces),
``inside_share`` (fraction of faces whose centroid projects inside the input's own mask: the object the input view
shows), ``above_share`` (fraction of faces whose centroid lies above the object's top by more than ``--above`` of
its height, default 0.10; the object = the faces projecting inside the mask) and ``white_share`` (vertices with
every colour channel >= 0.95: density the white background hides). For the faces off the mask,
``outside_edge_px`` gives how far their centroids project from it (pixels to the nearest mask pixel's centre:
median, 95th percentile, and the share within ``--edge`` pixels, default 3): a mesh a little wider than the
silhouette (within a pixel or two: the mask's own rounding, the surface's extraction) is not a floater.
Exit 1 when any mesh misses ``--min-object-share`` (default 0.95) or ``--min-main-share`` (default 0: off; 0.95
is the stricter gate that counts every detached piece as stray) or has a face above the limit, so it can gate a
release. The photo cannot vouch for what it does not see: a piece in front of the object, on its mask, counts as
shown.

    python scripts/mesh_check.py out/car out/chair
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
import trimesh
from PIL import Image
from scipy.spatial import cKDTree

from depthnerf.data.cameras import project, world_to_camera


def image_points(points: np.ndarray, c2w: np.ndarray, intrinsics: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points in the input image: ``(uv, in_front)``, the unrounded pixel coordinates (OpenCV camera ``c2w``;
    ``intrinsics`` = f, cx, cy, H, W; pixel (i, j) at (u, v) = (j, i); :mod:`depthnerf.data.cameras`) and whether
    each point is in front of the camera."""
    f, cx, cy = (float(x) for x in intrinsics[:3])
    cam = world_to_camera(torch.tensor(points, dtype=torch.float64), torch.tensor(c2w, dtype=torch.float64))
    return project(cam, f, (cx, cy)).numpy(), cam[:, 2].numpy() > 0


def inside_mask(points: np.ndarray, c2w: np.ndarray, intrinsics: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """True for world points that project (:func:`image_points`) in front of the camera onto a mask pixel."""
    h, w = int(intrinsics[3]), int(intrinsics[4])
    uv, front = image_points(points, c2w, intrinsics)
    u, v = np.round(uv).astype(np.int64).T
    ok = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    out = np.zeros(len(points), dtype=bool)
    out[ok] = mask[v[ok], u[ok]]
    return out


def edge_distance_px(points: np.ndarray, c2w: np.ndarray, intrinsics: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Pixels from each world point's projection (:func:`image_points`, unrounded) to the nearest mask pixel's
    centre; ``inf`` behind the camera or for an empty mask."""
    uv, front = image_points(points, c2w, intrinsics)
    out = np.full(len(points), np.inf)
    ij = np.argwhere(mask)
    if ij.size and front.any():
        out[front] = cKDTree(ij[:, ::-1].astype(np.float64)).query(uv[front])[0]
    return out


def visible_faces(mesh: trimesh.Trimesh, origin: np.ndarray) -> np.ndarray:
    """True for the faces whose centroid a camera at ``origin`` sees: the first face the ray from ``origin`` to the
    centroid meets is not nearer than the centroid (relative tolerance 1e-4 of its distance: embree hits in float32)."""
    centroids = np.asarray(mesh.triangles_center, dtype=np.float64)
    offsets = centroids - origin
    dist = np.linalg.norm(offsets, axis=1)
    hits, rays, _ = mesh.ray.intersects_location(np.repeat(origin[None], len(centroids), axis=0),
                                                 offsets / dist[:, None], multiple_hits=False)
    first = np.full(len(centroids), np.inf)
    first[rays] = np.linalg.norm(hits - origin, axis=1)
    return first >= dist * (1.0 - 1e-4)


def seen_pieces(labels: np.ndarray, main: int, shown: np.ndarray, min_seen: float) -> list[int]:
    """The piece labels other than ``main`` in which at least ``min_seen`` of the faces are ``shown`` (per face:
    visible from the input camera and on its mask)."""
    counts = np.bincount(labels)
    seen = np.bincount(labels, weights=shown.astype(np.float64), minlength=len(counts))
    return [k for k in range(len(counts)) if k != main and seen[k] >= min_seen * counts[k]]


def mesh_report(mesh: trimesh.Trimesh, c2w: np.ndarray, intrinsics: np.ndarray, mask: np.ndarray,
                above: float, edge: float = 3.0, min_seen: float = 0.25) -> dict:
    """Components, the largest one's face share, the detached pieces the photo shows, the faces on the input's mask
    and those above it (module docstring)."""
    if len(mesh.faces) == 0:
        return {"faces": 0, "components": 0, "main_share": 0.0, "seen_pieces": 0, "object_share": 0.0,
                "inside_share": 0.0, "above_share": 0.0, "white_share": 0.0, "outside_edge_px": None}
    centroids = mesh.triangles_center
    inside = inside_mask(centroids, c2w, intrinsics, mask)
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))
    counts = np.bincount(labels)
    main = int(np.argmax(counts))  # the first largest piece, as depthnerf.render.mesh.keep_pieces keeps
    shown = seen_pieces(labels, main, inside & visible_faces(mesh, np.asarray(c2w, np.float64)[:3, 3]), min_seen)
    in_object = np.isin(labels, [main, *shown])
    object_z = centroids[inside, 2] if inside.any() else centroids[:, 2]
    top, height = float(object_z.max()), float(object_z.max() - object_z.min())
    white = 0.0
    colors = getattr(mesh.visual, "vertex_colors", None)
    if colors is not None and len(colors) == len(mesh.vertices):
        white = float((np.asarray(colors)[:, :3] >= 0.95 * 255).all(axis=1).mean())
    off = None
    if not inside.all():
        dist = edge_distance_px(centroids[~inside], c2w, intrinsics, mask)
        off = {"median": float(np.median(dist)), "p95": float(np.percentile(dist, 95)),
               f"within_{edge:g}px_share": float((dist <= edge).mean())}
    return {"faces": int(len(mesh.faces)), "components": len(counts),
            "main_share": float(counts[main] / len(mesh.faces)), "seen_pieces": len(shown),
            "object_share": float(in_object.mean()), "inside_share": float(inside.mean()),
            "above_share": float((centroids[:, 2] > top + above * height).mean()), "white_share": white,
            "outside_edge_px": off}


def read_folder(path: Path) -> tuple[trimesh.Trimesh, np.ndarray, np.ndarray, np.ndarray]:
    """The mesh, the input camera (``depths.npz`` ``poses[0]`` and ``intrinsics``) and the input's mask of a
    reconstruct folder; a ValueError naming the file when one cannot be read."""
    def read(name: str, load):
        try:
            return load(path / name)
        except Exception as err:  # noqa: BLE001 - numpy, zipfile, PIL and trimesh each raise their own
            raise ValueError(f"{path / name}: unreadable ({type(err).__name__}: {err})") from None

    def cameras(file: Path):
        with np.load(file) as cams:
            return np.asarray(cams["poses"][0]), np.asarray(cams["intrinsics"])

    c2w, intrinsics = read("depths.npz", cameras)
    mask = read("input_mask.png", lambda f: np.asarray(Image.open(f).convert("L")) > 127)
    mesh = read("mesh.ply", lambda f: trimesh.load(f, process=False, force="mesh"))
    return mesh, c2w, intrinsics, mask


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("paths", nargs="+", type=Path, help="depthnerf reconstruct output folders")
    ap.add_argument("--above", type=float, default=0.10, help="stray-face margin above the main piece (heights)")
    ap.add_argument("--min-object-share", type=float, default=0.95,
                    help="least share of faces in the main piece and the detached pieces the photo shows")
    ap.add_argument("--min-main-share", type=float, default=0.0,
                    help="least share of faces in the main piece alone (0.95: every detached piece is stray)")
    ap.add_argument("--min-seen", type=float, default=0.25,
                    help="share of a detached piece's faces the input camera must see on its mask to show it")
    ap.add_argument("--edge", type=float, default=3.0, help="pixels from the mask that count as its edge")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    reports, ok = {}, True
    for path in args.paths:
        missing = [n for n in ("mesh.ply", "depths.npz", "input_mask.png") if not (path / n).is_file()]
        if missing:
            print(f"error: {path / missing[0]}: missing (not a depthnerf reconstruct folder with a mesh?)",
                  file=sys.stderr)
            return 2
        try:
            mesh, c2w, intrinsics, mask = read_folder(path)
        except ValueError as err:
            print(f"error: {err}", file=sys.stderr)
            return 2
        rep = mesh_report(mesh, c2w, intrinsics, mask, args.above, args.edge, args.min_seen)
        reports[str(path)] = rep
        ok &= (rep["object_share"] >= args.min_object_share and rep["main_share"] >= args.min_main_share
               and rep["above_share"] == 0.0)
        print(f"{path}: {rep['faces']} faces, {rep['components']} components, main piece {rep['main_share']:.1%}, "
              f"with the detached pieces the photo shows ({rep['seen_pieces']}) {rep['object_share']:.1%}, "
              f"on the input's mask {rep['inside_share']:.1%}, above the object {rep['above_share']:.1%}, "
              f"white vertices {rep['white_share']:.1%}")
        off = rep["outside_edge_px"]
        if off:
            print(f"  off the mask: {off['median']:.1f} px from it (median), {off['p95']:.1f} px (95th percentile), "
                  f"{off[f'within_{args.edge:g}px_share']:.1%} within {args.edge:g} px")
    if args.json:
        args.json.write_text(json.dumps(reports, indent=1) + "\n")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
