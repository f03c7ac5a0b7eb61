"""Cheap whole-file checks of SRN object folders and per-split summaries (what ``depthnerf inspect`` reports).

:func:`check_object` reads and checks **every** pose (16 finite numbers, a rigid transform) and opens every PNG
header without decoding pixels (PIL ``verify``: the chunk structure and CRCs are checked, so truncated or
corrupted files are caught, at ~1/5 of the cost of a decode). It also checks that every image, mask and depth map
has the ``H x W`` that ``intrinsics.txt`` states (depth: from the ``.npy`` header inside the ``.npz``, no
decompression of the array). Errors are :class:`~depthnerf.errors.DepthnerfError` with one line naming the file.

The *camera radius* of a view is the norm of its pose translation (the distance of the camera from the world
origin, where SRN objects are centred).
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from PIL import Image

from depthnerf.data.srn_format import read_pose
from depthnerf.errors import DepthnerfError

if TYPE_CHECKING:
    from depthnerf.data.srn import ObjectRecord, SplitIndex


@dataclass(frozen=True)
class ObjectCheck:
    """What :func:`check_object` measured on one object while checking it."""

    num_views: int
    """Number of views (image/pose pairs)."""
    radius_min: float
    """Smallest camera distance from the world origin over the object's views."""
    radius_max: float
    """Largest camera distance from the world origin over the object's views."""


def image_size(path: Path, what: str = "image") -> tuple[int, int]:
    """``(H, W)`` of an image file from its header; the whole file's structure is verified, pixels not decoded."""
    path = Path(path)
    try:
        with Image.open(path) as im:
            width, height = im.size
            im.verify()
    except FileNotFoundError:
        raise DepthnerfError(f"{path}: {what} file is missing") from None
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError) as err:
        raise DepthnerfError(f"{path}: unreadable {what} ({err})") from None
    return height, width


def depth_shape(path: Path) -> tuple[int, ...]:
    """Shape of the ``depth`` array in a depth ``.npz`` from its ``.npy`` header (no decompression, no pickle)."""
    path = Path(path)
    try:
        with zipfile.ZipFile(path) as archive, archive.open("depth.npy") as member:
            version = np.lib.format.read_magic(member)
            if version == (1, 0):
                shape, _, dtype = np.lib.format.read_array_header_1_0(member)
            else:
                shape, _, dtype = np.lib.format.read_array_header_2_0(member)
    except FileNotFoundError:
        raise DepthnerfError(f"{path}: depth file is missing") from None
    except KeyError:
        raise DepthnerfError(f"{path}: depth file has no 'depth' array") from None
    except (OSError, ValueError, zipfile.BadZipFile) as err:
        raise DepthnerfError(f"{path}: unreadable depth map ({err})") from None
    if dtype.hasobject:
        raise DepthnerfError(f"{path}: depth map holds Python objects, expected a float array")
    return tuple(shape)


def check_object(record: ObjectRecord) -> ObjectCheck:
    """Read every pose and open every image/mask/depth header of ``record``; raise on the first bad file."""
    intr = record.intrinsics
    expected = (intr.height, intr.width)
    radii = []
    for view in range(record.num_views):
        pose = read_pose(record.pose_path(view))
        radii.append(float(np.linalg.norm(pose[:3, 3])))
        checks = [(record.rgb_path(view), "image")]
        if record.has_mask:
            checks.append((record.mask_path(view), "mask"))
        for path, what in checks:
            size = image_size(path, what)
            if size != expected:
                raise DepthnerfError(f"{path}: {what} is {size[0]}x{size[1]} but {record.path / 'intrinsics.txt'}"
                                     f" says {expected[0]}x{expected[1]}")
        if record.has_depth:
            path = record.depth_path(view)
            shape = depth_shape(path)
            if shape != expected:
                raise DepthnerfError(f"{path}: depth map has shape {shape}, expected {expected} from intrinsics.txt")
    return ObjectCheck(num_views=record.num_views, radius_min=min(radii), radius_max=max(radii))


@dataclass(frozen=True)
class SplitSummary:
    """Per-split facts printed by ``depthnerf inspect`` (and written by ``--json``, via ``dataclasses.asdict``)."""

    category: str
    """Category name, from the ``<category>_<split>`` folder name."""
    split: str
    """``train``, ``val`` or ``test``."""
    path: str
    """The folder that holds the object folders (``chairs_train/chairs_2.0_train`` for SRN chairs)."""
    objects: int
    """Number of valid objects (skipped ones not counted)."""
    views_min: int
    """Fewest views of one object."""
    views_max: int
    """Most views of one object."""
    views_total: int
    """Views summed over objects."""
    resolution: list[int] | None
    """``[H, W]`` from ``intrinsics.txt`` when all objects agree, else ``None`` (see ``resolutions``)."""
    resolutions: list[list[int]]
    """Every distinct ``[H, W]`` in the split, sorted."""
    focal_min: float
    """Smallest focal length (pixels, at the on-disk resolution)."""
    focal_max: float
    """Largest focal length (pixels, at the on-disk resolution)."""
    radius_min: float | None
    """Smallest camera distance from the origin (``None`` if the files were not checked)."""
    radius_max: float | None
    """Largest camera distance from the origin (``None`` if the files were not checked)."""
    has_depth: bool
    """Every object has ``depth/`` z-depth maps."""
    has_mask: bool
    """Every object has ``mask/`` PNGs."""
    has_mesh: bool
    """Every object has ``mesh.ply``."""
    objects_with_depth: int
    """Objects with ``depth/``."""
    objects_with_mask: int
    """Objects with ``mask/``."""
    objects_with_mesh: int
    """Objects with ``mesh.ply``."""
    skipped: list[str]
    """One line per skipped object (file and problem); empty unless ``--skip-bad``."""


def summarize_split(index: SplitIndex) -> SplitSummary:
    """Summarise an indexed split; radii come from ``index.checks`` (filled by ``index_split(check_files=True)``)."""
    objs = index.objects
    views = [o.num_views for o in objs]
    sizes = sorted({(o.intrinsics.height, o.intrinsics.width) for o in objs})
    focals = [o.intrinsics.focal for o in objs]
    checks = [index.checks[o.object_id] for o in objs if o.object_id in index.checks]
    full = len(checks) == len(objs)
    n_depth = sum(o.has_depth for o in objs)
    n_mask = sum(o.has_mask for o in objs)
    n_mesh = sum(o.mesh_path is not None for o in objs)
    return SplitSummary(
        category=index.category, split=index.split, path=str(index.path), objects=len(objs),
        views_min=min(views), views_max=max(views), views_total=sum(views),
        resolution=list(sizes[0]) if len(sizes) == 1 else None, resolutions=[list(s) for s in sizes],
        focal_min=min(focals), focal_max=max(focals),
        radius_min=min(c.radius_min for c in checks) if full else None,
        radius_max=max(c.radius_max for c in checks) if full else None,
        has_depth=n_depth == len(objs), has_mask=n_mask == len(objs), has_mesh=n_mesh == len(objs),
        objects_with_depth=n_depth, objects_with_mask=n_mask, objects_with_mesh=n_mesh,
        skipped=list(index.skipped),
    )

