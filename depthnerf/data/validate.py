"""Cheap whole-file checks of SRN object folders and per-split summaries (what ``depthnerf inspect`` reports).

:func:`check_object` reads and checks **every** pose (16 finite numbers, a rigid transform) and opens every PNG
header without decoding pixels (PIL ``verify``: the chunk structure and CRCs are checked, so truncated or
corrupted files are caught, at ~1/5 of the cost of a decode). It checks that every image and mask has the
``H x W`` that ``intrinsics.txt`` states, reads every depth map whole (shape, NaN/inf, negative, all zero), and
reads ``mesh.ply`` whole (:func:`~depthnerf.data.mesh_file.check_mesh`: face indices in range, finite vertices;
only its header for training, which never uses it). Bad required files raise
:class:`~depthnerf.errors.DepthnerfError` with one line naming the file; a bad optional part is reported as a
:class:`~depthnerf.data.srn_parts.PartIssue` (or raises, with ``strict``). It also counts the file formats it saw;
an ``rgb/`` image that holds other data than PNG (a JPEG saved under a ``.png`` name), found from the header it
opens anyway, is listed for one warning per split (:func:`warn_rgb_not_png`), or raises with ``strict``.

The *camera radius* of a view is the norm of its pose translation (the distance of the camera from the world
origin, where SRN objects are centred). An object all of whose cameras look away from the origin (the camera's +z
axis, OpenCV's viewing direction, at more than 90 degrees from the direction to the origin) is refused: those are
OpenGL / Blender camera axes (looking down -z), which the loaders do not convert.
"""

from __future__ import annotations

import math
import warnings
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from depthnerf.data.mesh_file import check_mesh, check_mesh_header
from depthnerf.data.png_files import png_ihdr
from depthnerf.data.records import ObjectCheck, ObjectRecord, SplitIndex
from depthnerf.data.srn_format import (
    NOT_AN_IMAGE,
    check_cameras_face_origin,
    check_empty_depth,
    check_empty_mask,
    mask_not_png,
    read_depth,
    read_mask,
    read_pose,
    read_rgb,
)
from depthnerf.data.srn_parts import PART_LABELS, PartReport
from depthnerf.errors import DataWarning, DepthnerfError

PNG_COLOUR_TYPES = {0: "grey", 2: "RGB", 3: "palette", 4: "grey+alpha", 6: "RGBA"}
"""PNG ``IHDR`` colour types, as format names spell them."""

LOSSY_FORMATS = frozenset({"JPEG", "MPO"})
"""Image formats (Pillow's names) whose pixels are not the ones that were rendered (``MPO``: a camera's JPEG)."""


def _format_name(head: bytes, im: Image.Image) -> str:
    ihdr = png_ihdr(head)
    if ihdr is not None:
        return f"PNG {ihdr[0]}-bit {PNG_COLOUR_TYPES.get(ihdr[1], f'colour type {ihdr[1]}')}"
    return f"{im.format} {im.mode}"


def image_header(path: Path, what: str = "image") -> tuple[tuple[int, int], str]:
    """``(H, W)`` and format name (``"PNG 16-bit grey"``) of an image file from its header; the whole file's
    structure is verified, pixels not decoded."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(26)
            fh.seek(0)
            with Image.open(fh) as im:
                width, height = im.size
                name = _format_name(head, im)
                im.verify()
    except FileNotFoundError:
        raise DepthnerfError(f"{path}: {what} file is missing") from None
    except UnidentifiedImageError:
        raise DepthnerfError(f"{path}: unreadable {what} ({NOT_AN_IMAGE})") from None
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError) as err:
        raise DepthnerfError(f"{path}: unreadable {what} ({err})") from None
    return (height, width), name


def image_size(path: Path, what: str = "image") -> tuple[int, int]:
    """``(H, W)`` of an image file from its header (see :func:`image_header`)."""
    return image_header(path, what)[0]


def _size_checked(path: Path, what: str, expected: tuple[int, int], intrinsics: Path) -> str:
    size, name = image_header(path, what)
    if size != expected:
        raise DepthnerfError(f"{path}: {what} is {size[0]}x{size[1]} but {intrinsics} says {expected[0]}x{expected[1]}")
    return name


def not_png(name: str) -> str | None:
    """The file format (``"JPEG"``) of an :func:`image_header` format name when the file is not PNG data, else
    None: what a mask (refused) or an RGB image (read, with a warning) saved under a ``.png`` name really holds."""
    return None if name.startswith("PNG ") else name.split()[0]


def _lossy(fmt: str) -> str:
    """`` (lossy)`` for a format in :data:`LOSSY_FORMATS`, to end a message; else ``""``."""
    return " (lossy)" if fmt in LOSSY_FORMATS else ""


SIXTEEN_BIT_COLOUR = ("PNG 16-bit RGB", "PNG 16-bit RGBA")
"""Format names of the PNGs Pillow reads by their high bytes: their pixels are decoded when checked (8-bit values
stored in 16 bits read as zero)."""


def _mask_format(path: Path, expected: tuple[int, int], intrinsics: Path, image: Path) -> str:
    name = _size_checked(path, "mask", expected, intrinsics)
    if (fmt := not_png(name)) is not None:
        raise DepthnerfError(mask_not_png(path, fmt))
    if name in SIXTEEN_BIT_COLOUR:
        check_empty_mask(path, read_mask(path), image, read_rgb(image))
    return name


def _rgb_format(path: Path, expected: tuple[int, int], intrinsics: Path, strict: bool) -> tuple[str, str | None]:
    """Format name of an RGB image and, when it is not PNG data, its real format (an error with ``strict``)."""
    name = _size_checked(path, "image", expected, intrinsics)
    if name in SIXTEEN_BIT_COLOUR:
        read_rgb(path)
    fmt = not_png(name)
    if fmt is not None and strict:
        raise DepthnerfError(f"{path}: image holds {fmt} data under a .png name{_lossy(fmt)}; re-save it as PNG")
    return name, fmt


def _depth_format(name: str) -> str:
    return "16-bit PNG" if name.endswith(".png") else Path(name).suffix


def check_object(record: ObjectRecord, strict: bool = False, mesh_body: bool = True) -> ObjectCheck:
    """Read every pose, open every image/mask header, read every depth map and the mesh of ``record``.

    A bad required file raises on the first one; a bad optional part is reported once (its first bad file) in
    ``issues`` and not checked further, or raises with ``strict``. RGB images that are not PNG data are listed in
    ``rgb_not_png`` (the first one raises with ``strict``). ``mesh_body``: read ``mesh.ply`` whole
    (:func:`~depthnerf.data.mesh_file.check_mesh`); False: check only its header
    (:func:`~depthnerf.data.mesh_file.check_mesh_header`), for callers that never use the mesh (training,
    ``eval --no-mesh``).
    """
    intr = record.intrinsics
    expected = (intr.height, intr.width)
    intrinsics = record.path / "intrinsics.txt"
    report = PartReport(strict)
    radii = []
    rgb_not_png: list[tuple[str, Path]] = []
    rgb, masks, depths = Counter(), Counter(), Counter()
    masks_ok, depths_ok = record.has_mask, record.has_depth
    poses = []
    for view in range(record.num_views):
        pose = read_pose(record.pose_path(view))
        radii.append(float(np.linalg.norm(pose[:3, 3])))
        poses.append(pose)
        name, fmt = _rgb_format(record.rgb_path(view), expected, intrinsics, strict)
        rgb[name] += 1
        if fmt is not None:
            rgb_not_png.append((fmt, record.rgb_path(view)))
        if masks_ok:
            try:
                masks[_mask_format(record.mask_path(view), expected, intrinsics, record.rgb_path(view))] += 1
            except DepthnerfError as err:
                report.add_error("mask", record.mask_path(view), err)
                masks_ok = False
        if depths_ok:
            path = record.depth_path(view)
            try:
                depth = read_depth(path, record.depth_scale, expected, allow_empty=True)
                if not depth.any():
                    check_empty_depth(path, depth, record.rgb_path(view), read_rgb(record.rgb_path(view)))
                depths[_depth_format(path.name)] += 1
            except DepthnerfError as err:
                report.add_error("depth", path, err)
                depths_ok = False
    check_cameras_face_origin(record.pose_path(0), np.stack(poses))
    if record.mesh_path is not None:
        try:
            (check_mesh if mesh_body else check_mesh_header)(record.mesh_path)
        except DepthnerfError as err:
            report.add_error("mesh", record.mesh_path, err)
    return ObjectCheck(num_views=record.num_views, radius_min=min(radii), radius_max=max(radii),
                       rgb_formats=dict(rgb), mask_formats=dict(masks) if masks_ok else {},
                       depth_formats=dict(depths) if depths_ok else {}, issues=tuple(report.issues),
                       rgb_not_png=tuple(rgb_not_png))


def rgb_not_png_lines(index: SplitIndex) -> list[str]:
    """One line per format of the RGB files of ``index``'s checked objects that hold other data than PNG under
    their ``.png`` name: the split folder, how many files, the first one, and how they are read."""
    found: dict[str, list[Path]] = {}
    for record in index.objects:
        check = index.checks.get(record.object_id)
        for fmt, path in check.rgb_not_png if check is not None else ():
            found.setdefault(fmt, []).append(path)
    return [f"{index.path}: {len(paths):,} rgb {'file holds' if len(paths) == 1 else 'files hold'} {fmt} data under "
            f"a .png name (first: {paths[0]}); read as {fmt}{_lossy(fmt)}" for fmt, paths in found.items()]


def warn_rgb_not_png(index: SplitIndex) -> None:
    """Warn once per format (:func:`rgb_not_png_lines`) about the RGB files of a split that are not PNG data."""
    for line in rgb_not_png_lines(index):
        warnings.warn(line, DataWarning, stacklevel=3)


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
    rgb_formats: dict[str, int] = field(default_factory=dict)
    """Views per image format, e.g. ``{"PNG 8-bit RGBA": 251}`` (empty if the files were not checked)."""
    depth_formats: dict[str, int] = field(default_factory=dict)
    """Views per depth format (``.npz``, ``.npy``, ``16-bit PNG``) over the objects whose depth is usable."""
    mask_formats: dict[str, int] = field(default_factory=dict)
    """Views per mask format (e.g. ``PNG 1-bit grey``) over the objects whose masks are usable."""
    unusable: dict[str, int] = field(default_factory=dict)
    """Objects per optional part (``depth``, ``mask``, ``mesh``) that had the part but cannot use it."""
    warnings: list[str] = field(default_factory=list)
    """Every problem found in the optional parts, one line each (file and problem)."""
    ignored: dict[str, int] = field(default_factory=dict)
    """Entries of object folders the layout does not know (ignored), with the number of objects holding each."""


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
        rgb_formats=_sum_counts(c.rgb_formats for c in checks),
        depth_formats=_sum_counts(index.checks[o.object_id].depth_formats for o in objs
                                  if o.has_depth and o.object_id in index.checks),
        mask_formats=_sum_counts(index.checks[o.object_id].mask_formats for o in objs
                                 if o.has_mask and o.object_id in index.checks),
        unusable={part: n for part in PART_LABELS
                  if (n := sum(any(i.part == part and i.disables for i in o.issues) for o in objs))},
        warnings=[issue.message for issue in index.issues] + rgb_not_png_lines(index),
        ignored=dict(sorted(Counter(name for o in objs for name in o.ignored).items())),
    )


def _sum_counts(counts) -> dict[str, int]:
    total: Counter[str] = Counter()
    for c in counts:
        total.update(c)
    return dict(sorted(total.items()))



CARD_TOLERANCE = 1e-3
"""Relative tolerance when a dataset card's camera is compared with the files (``intrinsics.txt`` keeps 6 decimals)."""


def card_camera_disagreements(card: dict, card_file: str, summary: SplitSummary) -> list[str]:
    """Where a dataset card's ``camera`` (``height``/``width``, ``focal``, ``radius``) says other than a split's
    files: one line each, naming the card and the split. The files are what is read; a card that disagrees with
    them describes other data, and its ``pixel_center`` and framing may not hold for these files."""
    camera = card.get("camera")
    if not isinstance(camera, dict):
        return []

    def stated(key: str) -> float | None:
        value = camera.get(key)
        return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else None

    def off(value: float, low: float, high: float) -> bool:
        return not (low * (1 - CARD_TOLERANCE) <= value <= high * (1 + CARD_TOLERANCE))

    found = []
    size = [stated("height"), stated("width")]
    if None not in size and summary.resolutions and any(s != size for s in summary.resolutions):
        found.append(f"images {int(size[0])}x{int(size[1])}, the files "
                     + ", ".join(f"{h}x{w}" for h, w in summary.resolutions))
    focal = stated("focal")
    if focal is not None and off(focal, summary.focal_min, summary.focal_max):
        found.append(f"focal {focal:.4g} px, the files {_range(summary.focal_min, summary.focal_max)} px")
    radius = stated("radius")
    if radius is not None and summary.radius_min is not None and off(radius, summary.radius_min, summary.radius_max):
        found.append(f"cameras {radius:.4g} from the origin, the files "
                     f"{_range(summary.radius_min, summary.radius_max)}")
    if not found:
        return []
    return [f"{card_file}: the card's camera says {'; '.join(found)} ({summary.path}): the card describes other "
            "files, and its pixel_center and framing may not hold for these"]


def _range(low: float, high: float) -> str:
    return f"{low:.4g}" if math.isclose(low, high, rel_tol=CARD_TOLERANCE) else f"{low:.4g}-{high:.4g}"
