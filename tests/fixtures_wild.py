"""SRN-layout data as other people store it, for the reader tests (import from ``fixtures_wild``).

:func:`to_third_party_style` rewrites a fixture split the way independent renderers store the layout (depth as
``.npy`` or 16-bit PNG, 1-bit / 16-bit / RGBA / palette masks, extra files, another up axis).
:data:`BAD_OPTIONAL_CASES` break one optional part of one object.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh
from fixtures_srn import first_object
from PIL import Image

from depthnerf.data import srn_format


def _mask_size(root: Path) -> tuple[Path, str]:
    path = first_object(root) / "mask" / "000001.png"
    srn_format.write_mask(path, np.ones((20, 20), dtype=bool))
    return path, "mask is 20x20 but"


def _mask_truncated(root: Path) -> tuple[Path, str]:
    path = first_object(root) / "mask" / "000002.png"
    path.write_bytes(path.read_bytes()[:40])
    return path, "unreadable mask"


def _mask_stray(root: Path) -> tuple[Path, str]:
    path = first_object(root) / "mask" / "000000.jpg"
    path.write_bytes(b"jpeg")
    return path, "unexpected entry in mask/"


def _depth_array(name: str, array: np.ndarray, text: str):
    def mutate(root: Path) -> tuple[Path, str]:
        obj = first_object(root)
        (obj / "depth" / "000001.npz").unlink()
        path = obj / "depth" / name
        np.save(path, array)
        return path, text
    return mutate


def _depth_size(root: Path) -> tuple[Path, str]:
    path = first_object(root) / "depth" / "000001.npz"
    srn_format.write_depth(path, np.ones((20, 20), dtype=np.float32))
    return path, "depth map has shape (20, 20), expected 16x16"


def _depth_bytes(root: Path) -> tuple[Path, str]:
    path = first_object(root) / "depth" / "000002.npz"
    path.write_bytes(b"PK\x03\x04 not a zip")
    return path, "unreadable depth map"


def _missing_depth_view(root: Path) -> tuple[Path, str]:
    obj = first_object(root)
    (obj / "depth" / "000001.npz").unlink()
    return obj, "rgb/000001.png has no depth/000001.{npz,npy,png}"


def _depth_stray(root: Path) -> tuple[Path, str]:
    path = first_object(root) / "depth" / "000007.npz"
    path.write_bytes((path.parent / "000000.npz").read_bytes())
    return path, "unexpected entry in depth/ (no rgb/ image of that name)"


def _depth_exr(root: Path) -> tuple[Path, str]:
    obj = first_object(root)
    (obj / "depth" / "000001.npz").unlink()
    path = obj / "depth" / "000001.exr"
    path.write_bytes(b"v/1\x01 fake exr")
    return path, "EXR depth is not supported: no kept library reads OpenEXR"


def _depth_png_no_scale(root: Path) -> tuple[Path, str]:
    obj = first_object(root)
    depth = srn_format.read_depth(obj / "depth" / "000001.npz")
    (obj / "depth" / "000001.npz").unlink()
    path = obj / "depth" / "000001.png"
    write_depth_png16(path, depth, 1e-4)
    return path, "16-bit PNG depth needs a scale: write the world units per PNG unit"


def _depth_png_8bit_no_scale(root: Path) -> tuple[Path, str]:
    obj = first_object(root)
    (obj / "depth" / "000001.npz").unlink()
    path = obj / "depth" / "000001.png"
    Image.fromarray(np.full((16, 16), 40, np.uint8), mode="L").save(path)
    return path, "PNG depth must be 16-bit grey, got mode L"


def _depth_bad_scale(root: Path) -> tuple[Path, str]:
    _depth_png_no_scale(root)
    path = root / "cars_train" / srn_format.DEPTH_SCALE_FILE
    path.write_text("one millimetre\n")
    return path, "expected one positive number"


def _mesh_garbage(root: Path) -> tuple[Path, str]:
    path = first_object(root) / "mesh.ply"
    path.write_text("solid cube\nendsolid\n")
    return path, "not a PLY mesh"


def _mesh_truncated(root: Path) -> tuple[Path, str]:
    path = first_object(root) / "mesh.ply"
    data = path.read_bytes()
    assert b"format binary_little_endian" in data  # trimesh's export: a binary PLY, sized by its header
    path.write_bytes(data[: len(data) - 20])
    return path, "truncated PLY mesh"


def _mesh_face_out_of_range(root: Path) -> tuple[Path, str]:
    path = first_object(root) / "mesh.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                    "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
                    "0 0 0\n1 0 0\n0 1 0\n3 0 1 99\n")
    return path, "face 0 names vertex 99, but the mesh has 3 vertices"


def _mesh_nan_vertex(root: Path) -> tuple[Path, str]:
    path = first_object(root) / "mesh.ply"
    mesh = trimesh.load(path, force="mesh", process=False)
    mesh.vertices[1] = np.nan
    mesh.export(path)
    return path, "mesh has non-finite vertices"


BAD_OPTIONAL_CASES = {
    "mask_size_vs_intrinsics": ("mask", _mask_size),
    "mask_truncated": ("mask", _mask_truncated),
    "mask_stray_file": ("mask", _mask_stray),
    "depth_size_vs_intrinsics": ("depth", _depth_size),
    "depth_unreadable": ("depth", _depth_bytes),
    "depth_view_missing": ("depth", _missing_depth_view),
    "depth_stray_file": ("depth", _depth_stray),
    "depth_exr": ("depth", _depth_exr),
    "depth_png_without_scale": ("depth", _depth_png_no_scale),
    "depth_png_8bit_without_scale": ("depth", _depth_png_8bit_no_scale),
    "depth_scale_malformed": ("depth", _depth_bad_scale),
    "depth_nan_filled": ("depth", _depth_array("000001.npy", np.full((16, 16), np.nan, np.float32), "NaN or inf")),
    "depth_all_zero": ("depth", _depth_array("000001.npy", np.zeros((16, 16), np.float32), "all zero")),
    "depth_negative": ("depth", _depth_array("000001.npy", np.full((16, 16), -1.0, np.float32), "negative")),
    "depth_wrong_shape_npy": ("depth", _depth_array("000001.npy", np.ones((16, 15), np.float32), "shape (16, 15)")),
    "depth_integer_npy": ("depth", _depth_array("000001.npy", np.ones((16, 16), np.uint16), "expected floats")),
    "mesh_not_ply": ("mesh", _mesh_garbage),
    "mesh_truncated": ("mesh", _mesh_truncated),
    "mesh_face_out_of_range": ("mesh", _mesh_face_out_of_range),
    "mesh_nan_vertex": ("mesh", _mesh_nan_vertex),
}
"""Ways to break an *optional* part of the first train object of a ``make_srn_fixture(..., with_depth=True,
with_mask=True, with_mesh=True)`` folder: ``name -> (part, mutate)``; ``mutate(root)`` returns ``(path, text)``.
Indexing warns (``DataWarning`` naming ``path`` with ``text``) and turns ``part`` off for that object only; with
``strict=True`` it fails with a one-line message containing ``path`` and ``text``."""


def write_depth_png16(path: Path, depth: np.ndarray, scale: float) -> None:
    """Write z-depth as a 16-bit grey PNG of ``round(depth / scale)`` (0 stays 0)."""
    Image.fromarray(np.round(np.asarray(depth, np.float64) / scale).astype(np.uint16)).save(path)


BLENDER_WORLD = np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]], dtype=np.float64)
"""A world rotation taking +z up to +y up: the poses of a renderer with another up axis."""


def to_third_party_style(root: Path, png_scale: float = 1e-4) -> Path:
    """Rewrite the ``cars_train`` split of ``make_srn_fixture(root, with_depth=True, with_mask=True, with_mesh=True)``
    (at least 2 objects) the way independent renderers store the SRN layout; every loaded tensor stays the same
    except the poses (``BLENDER_WORLD @ pose``) and PNG depth (within ``png_scale / 2``):

    - object 0: depth as ``.npy``, 1-bit masks, plus ``render_log.txt``, ``meta.json`` and a ``normal/`` folder;
    - object 1: depth as 16-bit PNG (``depth_scale.txt`` in the split folder), 16-bit grey masks (value 1 = object);
    - other objects: RGBA masks (object where opaque), palette masks whose palette index 0 is *not* black.
    Every pose is rotated by :data:`BLENDER_WORLD` (another up axis), as if rendered in that world.
    """
    split = Path(root) / "cars_train"
    (split / srn_format.DEPTH_SCALE_FILE).write_text(f"{png_scale}\n")
    for k, obj in enumerate(sorted(p for p in split.iterdir() if p.is_dir())):
        for pose_file in sorted((obj / "pose").iterdir()):
            srn_format.write_pose(pose_file, BLENDER_WORLD @ srn_format.read_pose(pose_file))
        for depth_file in sorted((obj / "depth").iterdir()):
            depth = srn_format.read_depth(depth_file)
            if k == 0:
                np.save(depth_file.with_suffix(".npy"), depth)
                depth_file.unlink()
            elif k == 1:
                write_depth_png16(depth_file.with_suffix(".png"), depth, png_scale)
                depth_file.unlink()
        for mask_file in sorted((obj / "mask").iterdir()):
            mask = srn_format.read_mask(mask_file)
            if k == 0:
                Image.fromarray(mask).save(mask_file)  # mode "1"
            elif k == 1:
                Image.fromarray(mask.astype(np.uint16)).save(mask_file)  # 16-bit grey, 1 = object
            elif k % 2 == 0:
                rgba = np.zeros(mask.shape + (4,), np.uint8)
                rgba[..., :3], rgba[..., 3] = 200, np.where(mask, 255, 0)
                Image.fromarray(rgba).save(mask_file)
            else:
                pal = Image.fromarray(np.where(mask, 0, 1).astype(np.uint8))
                pal.putpalette([255, 255, 255, 0, 0, 0])  # "P"; index 0 = white = object, index 1 = black
                pal.save(mask_file)
        if k == 0:
            (obj / "render_log.txt").write_text("rendered with another tool\n")
            (obj / "meta.json").write_text("{}\n")
            (obj / "normal").mkdir()
            (obj / "normal" / "000000.png").write_bytes(b"")
    return root
