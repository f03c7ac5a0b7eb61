"""The SRN index records: what indexing a split folder finds, before any pixel is read.

:class:`ObjectRecord` (one object folder), :class:`SplitIndex` (one ``<category>_<split>`` folder) and
:class:`ObjectCheck` (what the whole-file checks of :func:`depthnerf.data.validate.check_object` measured). They
live here, below both :mod:`depthnerf.data.srn` (which builds them) and :mod:`depthnerf.data.validate` (which
checks and summarises them), so that neither imports the other for its types. ``depthnerf.data.srn`` still
exports ``SPLITS``, ``ObjectRecord`` and ``SplitIndex``, and ``depthnerf.data.validate`` ``ObjectCheck``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from depthnerf.data.cameras import Intrinsics
from depthnerf.data.srn_parts import PartIssue

SPLITS = ("train", "val", "test")
"""The split names of an SRN release, as they appear in ``<category>_<split>`` folder names."""


def in_dataset(path: Path, root: Path) -> bool:
    """Whether a folder ``path`` is the dataset ``root`` itself, or is or lies in one of its ``<category>_<split>``
    folders (one that exists or one so named), both resolved: where an output would be read back as an object or
    a split. A folder beside the splits (``root/runs``) is not."""
    path, root = Path(path).resolve(), Path(root).resolve()
    if path == root:
        return True
    if root not in path.parents:
        return False
    top = path.relative_to(root).parts[0]
    return top.rpartition("_")[2] in SPLITS


@dataclass(frozen=True)
class ObjectCheck:
    """What :func:`~depthnerf.data.validate.check_object` measured on one object while checking it."""

    num_views: int
    """Number of views (image/pose pairs)."""
    radius_min: float
    """Smallest camera distance from the world origin over the object's views."""
    radius_max: float
    """Largest camera distance from the world origin over the object's views."""
    rgb_formats: dict[str, int] = field(default_factory=dict)
    """Views per image format (e.g. ``"PNG 8-bit RGBA"``)."""
    mask_formats: dict[str, int] = field(default_factory=dict)
    """Views per mask format (usable masks only)."""
    depth_formats: dict[str, int] = field(default_factory=dict)
    """Views per depth format (``.npz``, ``.npy``, ``16-bit PNG``; usable depth only)."""
    issues: tuple[PartIssue, ...] = ()
    """Problems found in the optional parts (the parts they name are off for the object)."""
    rgb_not_png: tuple[tuple[str, Path], ...] = ()
    """``(format, file)`` of every ``rgb/`` image that holds other data than PNG (e.g. ``("JPEG", .../000000.png)``);
    such images are read as what they hold, with one warning per split."""


@dataclass(frozen=True)
class ObjectRecord:
    """Cheap index entry for one object folder: names and intrinsics, no pixels."""

    category: str
    """Category name (``cars``, ``chairs``, ...)."""
    split: str
    """One of :data:`SPLITS`."""
    object_id: str
    """Name of the object folder."""
    path: Path
    """The object folder."""
    view_names: tuple[str, ...]
    """File stems of the views, sorted (e.g. ``"000064"``)."""
    intrinsics: Intrinsics
    """As written in ``intrinsics.txt`` (at the on-disk resolution)."""
    has_depth: bool
    """``depth/`` holds a usable z-depth map for every view (as far as the checks that ran can tell)."""
    has_mask: bool
    """``mask/`` holds a usable mask for every view (as far as the checks that ran can tell)."""
    mesh_path: Path | None
    """``mesh.ply`` when present and usable."""
    depth_files: tuple[str, ...] = ()
    """File name in ``depth/`` of every view (empty: ``<stem>.npz``, the format this package writes)."""
    depth_scale: float | None = None
    """World units per unit of 16-bit PNG depth (from ``depth_scale.txt``); ``None`` when no view uses PNG."""
    issues: tuple[PartIssue, ...] = ()
    """Problems found in the optional parts (each part named by a disabling issue is off for this object)."""
    ignored: tuple[str, ...] = ()
    """Entries of the object folder that the layout does not know (ignored)."""

    @property
    def num_views(self) -> int:
        """Number of views."""
        return len(self.view_names)

    def rgb_path(self, view: int) -> Path:
        """``rgb/<stem>.png`` of view index ``view``."""
        return self.path / "rgb" / f"{self.view_names[view]}.png"

    def pose_path(self, view: int) -> Path:
        """``pose/<stem>.txt`` of view index ``view``."""
        return self.path / "pose" / f"{self.view_names[view]}.txt"

    def depth_path(self, view: int) -> Path:
        """The depth file of view index ``view`` (exists only if ``has_depth``); read it with
        ``srn_format.read_depth(path, record.depth_scale)`` (``allow_empty=True`` for views that show nothing)."""
        name = self.depth_files[view] if self.depth_files else f"{self.view_names[view]}.npz"
        return self.path / "depth" / name

    def mask_path(self, view: int) -> Path:
        """``mask/<stem>.png`` of view index ``view`` (exists only if ``has_mask``)."""
        return self.path / "mask" / f"{self.view_names[view]}.png"


@dataclass
class SplitIndex:
    """All objects of one ``<category>_<split>`` folder."""

    category: str
    """Category name."""
    split: str
    """One of :data:`SPLITS`."""
    path: Path
    """The folder holding the object folders (after the chairs nesting quirk)."""
    objects: list[ObjectRecord]
    """Valid objects, sorted by ``object_id``."""
    skipped: list[str]
    """One line (file and problem) per object skipped with ``skip_bad=True``."""
    checks: dict[str, ObjectCheck] = field(default_factory=dict)
    """Per ``object_id``: what the file checks measured (filled when indexed with ``check_files=True``)."""

    @property
    def issues(self) -> list[PartIssue]:
        """Every problem found in the optional parts of the (valid) objects."""
        return [issue for o in self.objects for issue in o.issues]
