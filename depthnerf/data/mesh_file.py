"""Reading and checking ``mesh.ply``, the optional ground-truth mesh of an SRN-format object.

:func:`check_mesh_header` is the cheap part: the file starts like a PLY with vertices and, when binary, is as
long as its header says. :func:`read_mesh` reads the whole file as one triangle mesh and checks what a reader
takes on trust: every face index names a vertex, every vertex is finite, and the triangles have area.
:func:`depthnerf.data.validate.check_object` runs both when a split is indexed (training and ``eval --no-mesh``,
which never use the mesh, only the header), so a bad mesh is a bad optional part (one warning naming the file, before
any object is rendered; the object is scored without it); evaluation reads the ground truth again with
:func:`read_mesh` when it scores the object (kept between the two, every mesh of a split would be in memory at
once). Every problem raises :class:`~depthnerf.errors.DepthnerfError` with one line naming the file.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import trimesh

from depthnerf.errors import DepthnerfError

PLY_SIZES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2, "uint16": 2,
             "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}
"""Bytes of each PLY scalar type."""


def check_mesh_header(path: Path) -> None:
    """Check that ``path`` starts like a PLY file with vertices (``ply``, ``element vertex N > 0``,
    ``end_header``) and, when binary, holds the bytes its header needs; :func:`read_mesh` checks the body."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(4096)
    except OSError as err:
        raise DepthnerfError(f"{path}: cannot read mesh ({err.strerror or err})") from None
    text = head.split(b"end_header")[0].decode("ascii", errors="replace")
    vertices = re.search(r"^element vertex (\d+)", text, flags=re.MULTILINE)
    if not head.startswith(b"ply") or b"end_header" not in head or not vertices or int(vertices.group(1)) == 0:
        raise DepthnerfError(f"{path}: not a PLY mesh with vertices (bad or missing header)")
    need = binary_ply_min_bytes(text)
    if need is not None:
        body = path.stat().st_size - (head.index(b"end_header") + len(b"end_header\n"))
        if body < need:
            raise DepthnerfError(f"{path}: truncated PLY mesh (its header needs at least {need} bytes of data, the "
                                 f"file has {max(body, 0)})")


def binary_ply_min_bytes(header: str) -> int | None:
    """The fewest data bytes a binary PLY ``header`` (its text before ``end_header``) describes: every element's
    fixed properties, and a list property as its count plus 3 entries (a face has at least 3 vertices); None for
    an ASCII PLY or a header this cannot size (an unknown type)."""
    if not re.search(r"^format binary_(little|big)_endian ", header, flags=re.MULTILINE):
        return None
    total, count, stride = 0, 0, 0
    for line in header.splitlines():
        words = line.split()
        if words[:1] == ["element"] and len(words) == 3 and words[2].isdigit():
            total, count, stride = total + count * stride, int(words[2]), 0
        elif words[:2] == ["property", "list"] and len(words) == 5:
            if words[2] not in PLY_SIZES or words[3] not in PLY_SIZES:
                return None
            stride += PLY_SIZES[words[2]] + 3 * PLY_SIZES[words[3]]
        elif words[:1] == ["property"] and len(words) == 3:
            if words[1] not in PLY_SIZES:
                return None
            stride += PLY_SIZES[words[1]]
    return total + count * stride


def mesh_problem(mesh: trimesh.Trimesh) -> str | None:
    """What makes ``mesh`` unusable as a ground truth (faces naming missing vertices, non-finite vertices, no
    triangle with area), or None."""
    faces, count = np.asarray(mesh.faces), len(mesh.vertices)
    if len(faces) and (faces.min() < 0 or faces.max() >= count):
        out = (faces < 0) | (faces >= count)
        row = int(np.flatnonzero(out.any(axis=1))[0])
        bad = int(faces[row][out[row]][0])
        more = f"; {int(out.any(axis=1).sum()) - 1} more faces do too" if out.any(axis=1).sum() > 1 else ""
        return f"face {row} names vertex {bad}, but the mesh has {count} vertices (0-{count - 1}){more}"
    if not np.isfinite(mesh.vertices).all():
        return "mesh has non-finite vertices"
    if not mesh.area > 0:
        return "mesh has no surface (its triangles have zero area)"
    return None


def read_mesh(path: Path) -> trimesh.Trimesh:
    """Read a mesh file (``mesh.ply`` of an SRN-format object) as one triangle mesh with at least one face, every
    face index in range, every vertex finite and some area (:func:`mesh_problem`)."""
    path = Path(path)
    if not path.is_file():
        raise DepthnerfError(f"{path}: mesh file not found")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as err:  # trimesh raises many types for malformed files
        raise DepthnerfError(f"{path}: cannot read mesh ({type(err).__name__}: {err})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise DepthnerfError(f"{path}: mesh has no triangles")
    problem = mesh_problem(mesh)
    if problem is not None:
        raise DepthnerfError(f"{path}: {problem}")
    return mesh


def check_mesh(path: Path) -> None:
    """Check ``mesh.ply`` whole: its header (:func:`check_mesh_header`), then its body (:func:`read_mesh`)."""
    check_mesh_header(path)
    read_mesh(path)
