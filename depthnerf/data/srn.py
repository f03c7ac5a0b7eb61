"""The ShapeNet SRN dataset as pixelNeRF reads it: a split index of object folders and per-object view loading.

Layout (file formats in :mod:`depthnerf.data.srn_format`)::

    <root>/<category>_<split>/<object_id>/{intrinsics.txt, rgb/NNNNNN.png, pose/NNNNNN.txt}
                                          [depth/NNNNNN.{npz,npy,png}, mask/NNNNNN.png, mesh.ply]

with ``split`` in :data:`SPLITS`. SRN quirk: the public chairs train set sits one level deeper,
``chairs_train/chairs_2.0_train/<object_id>/``; :func:`split_dir` resolves ``<c>_<s>/<c>_2.0_<s>/`` for every
category and split. Every sub-folder of a split folder is an object (plain files there are ignored), except hidden
ones (``.name``) and macOS zip residue (:data:`IGNORED_FOLDERS`).

Conventions, as in pixelNeRF's ``SRNDataset`` unless said otherwise:

- Views are the sorted file stems of ``rgb/*.png``; ``pose/*.txt`` must have exactly the same stems (an error
  otherwise, as for every problem with the required files). A view index is a position in that sorted list.
- Optional parts (``depth/``, ``mask/``, ``mesh.ply``; formats and rules in :mod:`depthnerf.data.srn_parts`): by
  default a problem in one makes that part unusable for that object, with a warning naming the file; with
  ``strict=True`` it is an error. Other entries of an object folder are ignored.
- Images are float ``[0, 1]``, alpha composited on white; 8- and 16-bit PNGs work (Pillow reads 16-bit *colour*
  PNGs at 8-bit precision, 16-bit grey at full precision).
- Poses stay camera-to-world with OpenCV axes (no flip to OpenGL axes; see :mod:`depthnerf.data.cameras`).
- Mask: ``mask/`` when present, else pixelNeRF's rule: a pixel is object unless its 8-bit value is 255 in *all*
  channels (``(img != 255).all(-1)``). Bbox: ``[x0, y0, x1, y1] = [cmin, rmin, cmax, rmax]`` of the mask,
  inclusive. **An all-white view** (the real SRN cars test set has one) gets an empty mask and the full-image box
  ``[0, 0, W-1, H-1]`` (pixelNeRF raises there; a full box just means "sample rays anywhere").
- Resizing (``load_object(resolution=...)``): images by area resampling (``F.interpolate(mode="area")``),
  intrinsics by :meth:`Intrinsics.resized` (exact for integer-centred pixels). A resized mask pixel is object when
  any of its footprint was object (area coverage > 0), so the mask and the bbox (recomputed from the resized mask)
  never cut off the object. Depth (0 = background) is resized as the area mean of the *valid* (non-zero) depths in
  each footprint, 0 where there are none, so background zeros never pull surfaces towards the camera.
"""

from __future__ import annotations

import sys
import warnings
from collections import Counter
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType

import numpy as np
import torch
import torch.nn.functional as F
from jaxtyping import Bool, Float, Int
from torch import Tensor
from tqdm import tqdm

from depthnerf.data import srn_format, srn_parts
from depthnerf.data.cameras import Intrinsics
from depthnerf.data.card import INTEGER_CENTRED
from depthnerf.data.records import SPLITS, ObjectRecord, SplitIndex
from depthnerf.data.srn_parts import PartReport
from depthnerf.data.validate import check_object, warn_rgb_not_png
from depthnerf.errors import DepthnerfError


@dataclass(frozen=True)
class CategoryDefaults:
    """Facts about how an SRN category was rendered (dataset facts, not model settings)."""

    z_near: float
    """Near bound of the ray distance used for rendering it (pixelNeRF's value)."""
    z_far: float
    """Far bound of the ray distance used for rendering it (pixelNeRF's value)."""
    camera_radius: float
    """Distance of the cameras from the object centre (world origin)."""
    focal: float
    """Focal length in pixels at ``image_size``."""
    image_size: int
    """Side of the square images of the release, in pixels."""


SRN_IMAGE_SIZE = 128
"""Side of the square images of SRN's releases (both categories), in pixels."""
SRN_FOCAL = 131.25
"""Focal length in pixels of SRN's images at :data:`SRN_IMAGE_SIZE` (525 / 512 * 128, as its intrinsics files
state; principal point at the image centre)."""
CATEGORY_DEFAULTS: Mapping[str, CategoryDefaults] = MappingProxyType({
    "cars": CategoryDefaults(z_near=0.8, z_far=1.8, camera_radius=1.3, focal=SRN_FOCAL, image_size=SRN_IMAGE_SIZE),
    "chairs": CategoryDefaults(z_near=1.25, z_far=2.75, camera_radius=2.0, focal=SRN_FOCAL,
                               image_size=SRN_IMAGE_SIZE),
})
"""Known SRN categories (read-only mapping)."""
IGNORED_FOLDERS: frozenset[str] = frozenset({"__MACOSX"})
"""Folders of a split folder that are never objects (besides hidden ones): ``__MACOSX`` is the resource-fork
residue macOS's zip writes next to the archived folders."""


def category_defaults(name: str) -> CategoryDefaults:
    """The :class:`CategoryDefaults` of a known category; a clear error for any other name."""
    try:
        return CATEGORY_DEFAULTS[name]
    except KeyError:
        known = ", ".join(sorted(CATEGORY_DEFAULTS))
        raise DepthnerfError(
            f"unknown SRN category {name!r} (known: {known}); SRN-format data of other categories still loads, "
            "but its z-range (z_near, z_far) must be given explicitly") from None


def split_dir(root: Path, category: str, split: str) -> Path:
    """``<root>/<category>_<split>``, or its ``<category>_2.0_<split>`` sub-folder when that exists (SRN chairs).

    Only resolves the path; :func:`index_split` reports a missing folder.
    """
    if split not in SPLITS:
        raise DepthnerfError(f"unknown split {split!r} (expected one of {', '.join(SPLITS)})")
    base = Path(root) / f"{category}_{split}"
    nested = base / f"{category}_2.0_{split}"
    return nested if nested.is_dir() else base


def ignored_folder(name: str) -> bool:
    """True for a folder of a split folder that is never an object: hidden (``.name``) or in
    :data:`IGNORED_FOLDERS`."""
    return name.startswith(".") or name in IGNORED_FOLDERS


def _root_above(split_folder: Path) -> Path:
    """The dataset root above a split folder (one level more for SRN's nested ``<c>_<s>/<c>_2.0_<s>/``)."""
    return split_folder.parent.parent if "_2.0_" in split_folder.name else split_folder.parent


def wrong_level(root: Path) -> str | None:
    """One error line when ``root`` is a split or an object folder rather than a dataset root (``--data`` a level
    or two too deep), else None."""
    root = Path(root)
    if not root.is_dir():
        return None
    category, _, split = root.name.rpartition("_")
    if split in SPLITS and category and (root / f"{category}_2.0_{split}").is_dir():
        level, above = "split", root.parent
    elif (root / "intrinsics.txt").is_file() or (root / "rgb").is_dir():
        level, above = "object", _root_above(root.parent)
    elif any((p / "intrinsics.txt").is_file() for p in root.iterdir() if p.is_dir()):
        level, above = "split", _root_above(root)
    else:
        return None
    return (f"{root}: is {'an' if level == 'object' else 'a'} {level} folder, not a dataset root; pass the folder "
            f"that holds the <category>_<split>/ folders (here probably {above})")


def discover_categories(root: Path) -> list[str]:
    """Sorted category names found as ``<category>_<split>`` folders directly under ``root`` (an error when
    ``root`` is a split or object folder: :func:`wrong_level`)."""
    root = Path(root)
    if root.exists() and not root.is_dir():
        raise DepthnerfError(f"{root}: is a file, not a dataset folder (pass the folder that holds the "
                             "<category>_<split>/ folders)")
    if not root.is_dir():
        raise DepthnerfError(f"{root}: dataset folder does not exist")
    found = set()
    for entry in root.iterdir():
        category, _, split = entry.name.rpartition("_")
        if entry.is_dir() and category and split in SPLITS and not entry.name.startswith("."):
            found.add(category)
    if not found or any(c.endswith("_2.0") for c in found):  # "chairs_2.0": root is SRN's chairs_train/
        hint = wrong_level(root)
        if hint is not None:
            raise DepthnerfError(hint)
    return sorted(found)


def _stems(folder: Path, suffix: str) -> list[str]:
    """Sorted stems of the ``*suffix`` files in ``folder``; any other (non-hidden) entry is an error."""
    stems = []
    for entry in folder.iterdir():
        if entry.name.startswith("."):
            continue
        if entry.suffix != suffix or not entry.is_file():
            raise DepthnerfError(f"{entry}: unexpected entry in {folder.name}/ (expected only *{suffix} files)")
        stems.append(entry.stem)
    return sorted(stems)


def _pair(obj: Path, names: list[str], folder: str, suffix: str) -> None:
    """Check that ``<obj>/<folder>`` has exactly one ``*suffix`` file per view stem in ``names``."""
    other = _stems(obj / folder, suffix)
    if other == names:
        return
    missing = sorted(set(names) - set(other))
    extra = sorted(set(other) - set(names))
    example = (f"rgb/{missing[0]}.png has no {folder}/{missing[0]}{suffix}" if missing
               else f"{folder}/{extra[0]}{suffix} has no rgb/{extra[0]}.png")
    raise DepthnerfError(f"{obj}: {len(names)} images in rgb/ but {len(other)} files in {folder}/ "
                         f"that do not pair up by name (e.g. {example})")


def index_object(path: Path, category: str, split: str, *, strict: bool = False, root: Path | None = None
                 ) -> ObjectRecord:
    """Index one object folder: read ``intrinsics.txt``, pair the view files by name (no per-view reads).

    Required files raise :class:`DepthnerfError`; problems of the optional parts are kept in ``issues`` (and that
    part is off), or raise with ``strict``. ``root``: the dataset root, up to which ``depth_scale.txt`` is looked
    for (see :func:`~depthnerf.data.srn_parts.scale_dirs`).
    """
    path = Path(path)
    intrinsics = srn_format.read_intrinsics(path / "intrinsics.txt")
    for folder in ("rgb", "pose"):
        if not (path / folder).is_dir():
            raise DepthnerfError(f"{path}: missing {folder}/ folder")
    names = _stems(path / "rgb", ".png")
    if not names:
        raise DepthnerfError(f"{path / 'rgb'}: no .png images")
    _pair(path, names, "pose", ".txt")
    report = PartReport(strict)
    depth_files, depth_scale = srn_parts.list_depth(path, names, report, srn_parts.scale_dirs(path, root))
    has_mask = srn_parts.list_mask(path, names, report)
    mesh = srn_parts.find_mesh(path, report)
    return ObjectRecord(category=category, split=split, object_id=path.name, path=path, view_names=tuple(names),
                        intrinsics=intrinsics, has_depth=bool(depth_files), has_mask=has_mask, mesh_path=mesh,
                        depth_files=depth_files, depth_scale=depth_scale, issues=tuple(report.issues),
                        ignored=srn_parts.extras(path))


def object_dirs(root: Path, category: str, split: str) -> list[Path]:
    """The object folders of ``<root>/<category>_<split>``, sorted by name (an object's id is its folder's name);
    one line naming the path when the dataset or split folder is missing, a file, or the split is empty."""
    folder = split_dir(root, category, split)
    if not folder.is_dir():
        if Path(root).exists() and not Path(root).is_dir():
            raise DepthnerfError(f"{root}: is a file, not a dataset folder (pass the folder that holds "
                                 f"{category}_{split}/)")
        if not Path(root).exists():
            raise DepthnerfError(f"{root}: dataset folder does not exist")
        hint = wrong_level(root)
        if hint is not None:
            raise DepthnerfError(hint)
        problem = "is a file, not a split folder" if folder.exists() else "split folder does not exist"
        raise DepthnerfError(f"{folder}: {problem}")
    found = sorted(p for p in folder.iterdir() if p.is_dir() and not ignored_folder(p.name))
    if not found:
        raise DepthnerfError(f"{folder}: empty split (no object folders)")
    return found


def index_split(root: Path, category: str, split: str, *, skip_bad: bool = False, check_files: bool = True,
                progress: bool = False, strict: bool = False, only: Collection[str] | None = None,
                mesh_body: bool = True) -> SplitIndex:
    """Index ``<root>/<category>_<split>``.

    Always: reads every ``intrinsics.txt`` and pairs view files by name. ``check_files``: also reads and checks
    every pose, opens every image header and reads every depth map (see
    :func:`~depthnerf.data.validate.check_object`). A bad required file raises :class:`DepthnerfError`, or with
    ``skip_bad`` its object is left out and listed in ``skipped``. A bad optional part is off for its object, with
    a :class:`~depthnerf.errors.DataWarning` (grouped per split), or with ``strict`` an error. A checked ``rgb/``
    image holding other data than PNG (a JPEG under a ``.png`` name) is read as what it holds, with one warning
    per split (first file, count), or with ``strict`` an error. A split without usable objects is an error.
    ``only``: index just the objects of these ids (names from :func:`object_dirs`; None: every object).
    ``mesh_body``: with ``check_files``, read every ``mesh.ply`` whole; False checks only its header (training and
    ``eval --no-mesh``, which never use the mesh; ``strict`` always reads it whole).
    ``progress`` shows a tqdm bar on stderr (when it is a terminal).
    """
    folder = split_dir(root, category, split)
    dirs = object_dirs(root, category, split)
    if only is not None:
        dirs = [p for p in dirs if p.name in only]
        if not dirs:
            raise DepthnerfError(f"{folder}: none of the objects asked for is here ({', '.join(sorted(only))})")
    index = SplitIndex(category=category, split=split, path=folder, objects=[], skipped=[])
    bar = tqdm(dirs, desc=f"{category}_{split}", unit="obj", file=sys.stderr, leave=False,
               disable=None if progress else True)
    for obj_dir in bar:
        try:
            record = index_object(obj_dir, category, split, strict=strict, root=root)
            if check_files:
                check = check_object(record, strict=strict, mesh_body=mesh_body or strict)
                index.checks[record.object_id] = check
                record = srn_parts.with_issues(record, check.issues)
        except DepthnerfError as err:
            if not skip_bad:
                raise
            index.skipped.append(str(err))
            continue
        index.objects.append(record)
    if not index.objects:
        raise DepthnerfError(f"{folder}: no usable objects ({len(index.skipped)} skipped; first: {index.skipped[0]})")
    srn_parts.warn_split(folder, [o.issues for o in index.objects], Counter(n for o in index.objects for n in o.ignored))
    warn_rgb_not_png(index)
    return index


@dataclass
class ObjectViews:
    """Some views of one object, loaded (what the training data loader returns per object)."""

    record: ObjectRecord
    """The index entry the views came from."""
    view_indices: Int[Tensor, " V"]
    """Indices into ``record.view_names`` of the loaded views, in load order."""
    images: Float[Tensor, "V 3 H W"]
    """RGB in ``[0, 1]``, composited on white."""
    poses: Float[Tensor, "V 4 4"]
    """Camera-to-world, OpenCV camera axes."""
    intrinsics: Intrinsics
    """Intrinsics of the returned images (after any resize)."""
    masks: Bool[Tensor, "V H W"]
    """Object pixels (see the module docstring for the rule and for resizing)."""
    bboxes: Int[Tensor, "V 4"]
    """``[x0, y0, x1, y1]`` of the mask, inclusive; the full image for an empty mask."""
    depths: Float[Tensor, "V H W"] | None
    """Ground-truth z-depth, 0 = background (``with_depth=True`` only); resized by valid-depth area mean."""


def mask_bboxes(masks: Bool[Tensor, "V H W"]) -> Int[Tensor, "V 4"]:
    """``[x0, y0, x1, y1]`` (inclusive) of each mask; ``[0, 0, W-1, H-1]`` for an empty mask."""
    m = masks.detach().cpu().numpy()  # numpy's any() is ~100x faster than torch's on bool tensors
    _, height, width = m.shape
    rows, cols = m.any(axis=2), m.any(axis=1)
    # argmax returns the first maximal index: the first / last row and column that hold object pixels.
    boxes = np.stack([cols.argmax(1), rows.argmax(1), width - 1 - cols[:, ::-1].argmax(1),
                      height - 1 - rows[:, ::-1].argmax(1)], axis=1)
    boxes[~rows.any(axis=1)] = [0, 0, width - 1, height - 1]
    return torch.from_numpy(boxes.astype(np.int64))


def _view_indices(record: ObjectRecord, views: Sequence[int] | None) -> list[int]:
    if views is None:
        return list(range(record.num_views))
    out = [int(v) for v in views]
    if not out:
        raise DepthnerfError(f"{record.path}: no views requested")
    bad = [v for v in out if not 0 <= v < record.num_views]
    if bad:
        raise DepthnerfError(f"{record.path}: view index {bad[0]} out of range (object has {record.num_views} views)")
    return out


def _resized(intr: Intrinsics, height: int, width: int, where: Path) -> Intrinsics:
    try:
        return intr.resized(height, width)
    except ValueError as err:
        raise DepthnerfError(f"{where}: cannot resize ({err})") from None


def _resample(images: Float[Tensor, "V 3 H W"], masks: Bool[Tensor, "V H W"], depths: Float[Tensor, "V H W"] | None,
              size: tuple[int, int]) -> tuple[Tensor, Tensor, Tensor | None]:
    """Area-resample images, masks (coverage > 0) and depths (mean of the valid depths) to ``size``."""
    images = F.interpolate(images, size=size, mode="area")
    masks = F.interpolate(masks[:, None].float(), size=size, mode="area")[:, 0] > 0
    if depths is not None:
        valid = (depths > 0).float()[:, None]
        total = F.interpolate(depths[:, None] * valid, size=size, mode="area")[:, 0]
        cover = F.interpolate(valid, size=size, mode="area")[:, 0]
        depths = torch.where(cover > 0, total / cover.clamp_min(1e-12), torch.zeros_like(total))
    return images, masks, depths


def load_object(record: ObjectRecord, views: Sequence[int] | None = None, *, resolution: int | None = None,
                with_depth: bool = False, check_size: bool = True, pixel_center: float | None = None) -> ObjectViews:
    """Load views of one object (all by default) as tensors; see the module docstring for the conventions.

    ``resolution``: output height (width scales with it; SRN images are square), area resampling.
    ``with_depth``: also load ``depth/`` (an error if the object has none).
    ``check_size``: an image whose size differs from ``intrinsics.txt`` is an error; with ``False`` the
    intrinsics are instead rescaled to the decoded size (which must be a uniform rescale).
    ``pixel_center``: the data's pixel (i, j) is centred at ``(j + c, i + c)`` in ``intrinsics.txt``'s coordinates;
    the returned intrinsics are integer-centred (shifted by ``c`` at the file's resolution, then resized). Callers
    state it (a checkpoint's ``InferenceSpec.pixel_center``, a run's ``data.pixel_center``, or
    :data:`~depthnerf.data.card.INTEGER_CENTRED` where only pixels are read); without it the files are read
    integer-centred, with a warning saying so.
    """
    if pixel_center is None:
        warnings.warn("load_object: no pixel centre stated; intrinsics.txt read integer-centred (pixel (i, j) at "
                      "(j, i), pixel_center 0.0, pixelNeRF's reading); pass pixel_center=", stacklevel=2)
        pixel_center = INTEGER_CENTRED
    indices = _view_indices(record, views)
    if with_depth and not record.has_depth:
        raise DepthnerfError(f"{record.path}: no depth/ folder, or not a usable one (ground-truth depth requested)")
    images = [srn_format.read_rgb(record.rgb_path(v)) for v in indices]
    height, width = images[0].shape[:2]
    for v, img in zip(indices, images, strict=True):
        if img.shape[:2] != (height, width):
            raise DepthnerfError(f"{record.rgb_path(v)}: image is {img.shape[0]}x{img.shape[1]} but "
                                 f"{record.rgb_path(indices[0]).name} is {height}x{width}")
    intr = record.intrinsics.with_pixel_center(pixel_center)
    if (height, width) != (intr.height, intr.width):
        if check_size:
            raise DepthnerfError(f"{record.rgb_path(indices[0])}: image is {height}x{width} but "
                                 f"{record.path / 'intrinsics.txt'} says {intr.height}x{intr.width}")
        intr = _resized(intr, height, width, record.path)
    if record.has_mask:
        masks = [srn_format.read_mask(record.mask_path(v)) for v in indices]
        for v, img, mask in zip(indices, images, masks, strict=True):
            srn_format.check_empty_mask(record.mask_path(v), mask, record.rgb_path(v), img)
    else:
        masks = [srn_format.mask_from_white(img) for img in images]
    depths = None
    if with_depth:
        depths = [srn_format.read_depth(record.depth_path(v), record.depth_scale, allow_empty=True) for v in indices]
        for v, img, depth in zip(indices, images, depths, strict=True):
            srn_format.check_empty_depth(record.depth_path(v), depth, record.rgb_path(v), img)
    for kind, arrays, path_of in (("mask", masks, record.mask_path), ("depth map", depths or [], record.depth_path)):
        for v, arr in zip(indices, arrays, strict=False):
            if arr.shape != (height, width):
                raise DepthnerfError(f"{path_of(v)}: {kind} is {arr.shape[0]}x{arr.shape[1]} but the image is "
                                     f"{height}x{width}")
    poses = np.stack([srn_format.read_pose(record.pose_path(v)) for v in indices])
    srn_format.check_cameras_face_origin(record.pose_path(indices[0]), poses)
    images_t = torch.from_numpy(np.stack(images)).permute(0, 3, 1, 2).contiguous()
    masks_t = torch.from_numpy(np.stack(masks))
    depths_t = torch.from_numpy(np.stack(depths)) if depths is not None else None
    if resolution is not None and resolution != height:
        new_width = resolution * width / height
        if resolution <= 0 or new_width != int(new_width):
            raise DepthnerfError(f"{record.path}: cannot resize {height}x{width} images to height {resolution} "
                                 "(the width would not be a whole number of pixels)")
        images_t, masks_t, depths_t = _resample(images_t, masks_t, depths_t, (resolution, int(new_width)))
        intr = _resized(intr, resolution, int(new_width), record.path)
    return ObjectViews(record=record, view_indices=torch.tensor(indices, dtype=torch.long), images=images_t,
                       poses=torch.from_numpy(poses), intrinsics=intr, masks=masks_t, bboxes=mask_bboxes(masks_t),
                       depths=depths_t)
