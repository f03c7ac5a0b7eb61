"""The optional parts of an SRN object folder (``depth/``, ``mask/``, ``mesh.ply``) and the entries it may hold
that the layout does not know.

Lenient (the default): a problem in an optional part (a file that is unreadable, unexpected, missing for some
view, of the wrong size, or holds invalid depth) makes that part unusable **for that object**; the problem is
kept as a :class:`PartIssue` (one line naming the file) and :func:`warn_split` turns the issues of a split into
:class:`~depthnerf.errors.DataWarning` lines, one per kind of problem. Strict: the first problem raises
:class:`~depthnerf.errors.DepthnerfError`. Required files (``intrinsics.txt``, ``rgb/``, ``pose/``) are not handled
here: they are always strict (:mod:`depthnerf.data.srn`).

Depth is looked up per view by file stem, so formats may be mixed in one ``depth/`` folder; a view with files in
two formats uses the first of :data:`~depthnerf.data.srn_format.DEPTH_SUFFIXES` (a warning names the other).
16-bit PNG depth takes its scale from the nearest ``depth_scale.txt`` in the object folder, the split folder or
the dataset root. Entries of an object folder outside :data:`KNOWN_ENTRIES` are ignored in both modes (one
:class:`~depthnerf.errors.DataNote` per split).
"""

from __future__ import annotations

import re
import warnings
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

from depthnerf.data.srn_format import (
    DEPTH_SCALE_FILE,
    DEPTH_SUFFIXES,
    EXR_UNSUPPORTED,
    check_png_depth_mode,
    read_depth_scale,
)
from depthnerf.errors import DataNote, DataWarning, DepthnerfError

KNOWN_ENTRIES = frozenset({"intrinsics.txt", "rgb", "pose", "depth", "mask", "mesh.ply", DEPTH_SCALE_FILE})
"""Names an object folder may hold; anything else is ignored (and noted once per split)."""

PART_LABELS = {"depth": "depth/", "mask": "mask/", "mesh": "mesh.ply"}
"""The optional parts, by the name :class:`PartIssue` uses, and how messages spell them."""


@dataclass(frozen=True)
class PartIssue:
    """One problem found in an optional part of one object."""

    part: str
    """``depth``, ``mask`` or ``mesh`` (keys of :data:`PART_LABELS`)."""
    path: Path
    """The file or folder with the problem."""
    text: str
    """One line: the path, then the problem."""
    disables: bool = True
    """The part is not used for the object (``False``: only a warning, e.g. a view stored in two formats)."""

    @property
    def message(self) -> str:
        """The warning line: the problem and what it costs."""
        return self.text + (f"; {PART_LABELS[self.part]} not used for this object" if self.disables else "")

    @property
    def kind(self) -> str:
        """Groups equal problems across objects: the part and the problem's first words, digits masked."""
        problem = self.text.removeprefix(f"{self.path}: ")
        return self.part + ": " + " ".join(re.sub(r"\d+", "#", problem).split()[:4])


class PartReport:
    """Collects the :class:`PartIssue` of one object; with ``strict`` the first one raises instead."""

    def __init__(self, strict: bool) -> None:
        self.strict = strict
        self.issues: list[PartIssue] = []

    def add(self, part: str, path: Path, text: str, disables: bool = True) -> None:
        """Record a problem (``text``: one line starting with ``path``), or raise it when strict."""
        if self.strict:
            raise DepthnerfError(text)
        self.issues.append(PartIssue(part=part, path=Path(path), text=text, disables=disables))

    def add_error(self, part: str, path: Path, err: DepthnerfError) -> None:
        """Record a reader's error as a problem of ``part`` (re-raised when strict)."""
        self.add(part, path, str(err))


def scale_dirs(obj: Path, root: Path | None) -> list[Path]:
    """Where ``depth_scale.txt`` is looked for, nearest first: the object folder and its ancestors up to
    ``root`` (the dataset root; without it, the object folder and its split folder)."""
    dirs = [obj]
    if root is None:
        return dirs + [obj.parent]
    root = Path(root)
    for parent in obj.parents:
        dirs.append(parent)
        if parent == root or len(dirs) > 4:
            break
    return dirs


def _depth_scale(first_png: Path, dirs: Sequence[Path], report: PartReport) -> float | None:
    for folder in dirs:
        path = folder / DEPTH_SCALE_FILE
        if path.is_file():
            try:
                return read_depth_scale(path)
            except DepthnerfError as err:
                report.add_error("depth", path, err)
                return None
    try:
        check_png_depth_mode(first_png)  # a scale cannot help an 8-bit PNG: say that first
    except DepthnerfError as err:
        report.add_error("depth", first_png, err)
        return None
    report.add("depth", first_png, f"{first_png}: 16-bit PNG depth needs a scale: write the world units per PNG "
               f"unit (e.g. 0.001) into {DEPTH_SCALE_FILE} in the object, split or dataset folder")
    return None


def _per_view_files(obj: Path, names: Sequence[str], part: str, suffixes: Sequence[str],
                    report: PartReport) -> dict[str, list[str]] | None:
    """``{view stem: [file names]}`` of ``obj/<part>/``, or None after reporting the first problem."""
    folder = obj / part
    if not folder.is_dir():
        report.add(part, folder, f"{folder}: not a folder")
        return None
    wanted = set(names)
    by_stem: dict[str, list[str]] = {}
    expected = " / ".join(f"<view>{s}" for s in suffixes)
    for entry in sorted(folder.iterdir()):
        if entry.name.startswith("."):
            continue
        if part == "depth" and entry.suffix.lower() == ".exr":
            report.add(part, entry, f"{entry}: {EXR_UNSUPPORTED}")
            return None
        if not entry.is_file() or entry.suffix not in suffixes or entry.stem not in wanted:
            why = "not a file" if not entry.is_file() else (
                "no rgb/ image of that name" if entry.suffix in suffixes else f"expected {expected}")
            report.add(part, entry, f"{entry}: unexpected entry in {part}/ ({why})")
            return None
        by_stem.setdefault(entry.stem, []).append(entry.name)
    missing = [n for n in names if n not in by_stem]
    if missing:
        spelled = suffixes[0] if len(suffixes) == 1 else ".{" + ",".join(s[1:] for s in suffixes) + "}"
        report.add(part, obj, f"{obj}: rgb/{missing[0]}.png has no {part}/{missing[0]}{spelled} "
                   f"({len(missing)} of {len(names)} views have none)")
        return None
    return by_stem


def list_depth(obj: Path, names: Sequence[str], report: PartReport, scale_search: Sequence[Path]
               ) -> tuple[tuple[str, ...], float | None]:
    """The depth file name of every view of ``obj`` (empty when ``depth/`` is absent or unusable) and the PNG
    depth scale (``None`` when no view uses PNG)."""
    if not (obj / "depth").exists():
        return (), None
    by_stem = _per_view_files(obj, names, "depth", DEPTH_SUFFIXES, report)
    if by_stem is None:
        return (), None
    rank = {s: i for i, s in enumerate(DEPTH_SUFFIXES)}
    chosen = [min(by_stem[n], key=lambda f: rank[Path(f).suffix]) for n in names]
    doubles = [(n, c) for n, c in zip(names, chosen, strict=True) if len(by_stem[n]) > 1]
    if doubles:
        stem, used = doubles[0]
        other = next(f for f in by_stem[stem] if f != used)
        report.add("depth", obj / "depth" / other, f"{obj / 'depth' / other}: view {stem} also has depth/{used}, "
                   f"which is used ({len(doubles)} views have depth in two formats)", disables=False)
    pngs = [f for f in chosen if f.endswith(".png")]
    if not pngs:
        return tuple(chosen), None
    scale = _depth_scale(obj / "depth" / pngs[0], scale_search, report)
    return (tuple(chosen), scale) if scale is not None else ((), None)


def list_mask(obj: Path, names: Sequence[str], report: PartReport) -> bool:
    """Whether ``obj/mask/`` holds one PNG per view (problems go to ``report``)."""
    if not (obj / "mask").exists():
        return False
    return _per_view_files(obj, names, "mask", (".png",), report) is not None


def find_mesh(obj: Path, report: PartReport) -> Path | None:
    """``obj/mesh.ply`` when it is a file (its content is checked by :mod:`depthnerf.data.validate`)."""
    path = obj / "mesh.ply"
    if not path.exists():
        return None
    if not path.is_file():
        report.add("mesh", path, f"{path}: not a file")
        return None
    return path


def extras(obj: Path) -> tuple[str, ...]:
    """Sorted entries of ``obj`` that the layout does not know (folders with a trailing ``/``), hidden ones aside."""
    return tuple(sorted(e.name + "/" * e.is_dir() for e in obj.iterdir()
                        if e.name not in KNOWN_ENTRIES and not e.name.startswith(".")))


def unusable_parts(issues: Iterable[PartIssue]) -> set[str]:
    """The parts that ``issues`` make unusable."""
    return {i.part for i in issues if i.disables}


def with_issues(record, issues: Sequence[PartIssue]):
    """An :class:`~depthnerf.data.records.ObjectRecord` with ``issues`` added and the parts they disable turned
    off."""
    if not issues:
        return record
    off = unusable_parts(issues)
    depth = "depth" not in off
    return replace(record, has_depth=record.has_depth and depth, depth_files=record.depth_files if depth else (),
                   depth_scale=record.depth_scale if depth else None, has_mask=record.has_mask and "mask" not in off,
                   mesh_path=None if "mesh" in off else record.mesh_path, issues=record.issues + tuple(issues))


def warn_split(folder: Path, issues: Sequence[Sequence[PartIssue]], ignored: Counter[str]) -> None:
    """Warn about a split: one :class:`DataWarning` per kind of problem (the first object's file named, with how
    many more objects share it) and one :class:`DataNote` listing the ignored entries. ``issues``: per object."""
    groups: dict[str, list[PartIssue]] = {}
    for object_issues in issues:
        for issue in object_issues:
            groups.setdefault(issue.kind, []).append(issue)
    for group in groups.values():
        more = f" (the same in {len(group) - 1} more objects of {folder})" if len(group) > 1 else ""
        warnings.warn(group[0].message + more, DataWarning, stacklevel=3)
    if ignored:
        names = ", ".join(f"{name} ({count})" for name, count in sorted(ignored.items()))
        warnings.warn(f"{folder}: ignored entries the SRN layout does not use (objects holding each): {names}", DataNote,
                      stacklevel=3)
