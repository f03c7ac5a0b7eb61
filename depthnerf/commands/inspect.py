"""``depthnerf inspect --data DIR``: validate an SRN-format dataset folder and summarise each split.

Every ``<category>_<split>`` folder under ``DIR`` (or only ``--category`` / ``--split``) is indexed with every
pose read and checked and every PNG header opened and size-checked (:func:`depthnerf.data.srn.index_split`).
The first bad *required* file (intrinsics, rgb, pose) stops the run with ``error: <file>: <problem>`` (exit 2)
unless ``--skip-bad``, which leaves bad objects out and lists them. A bad *optional* part (depth, mask, mesh) is
not used for that object, with a ``warning: <file>: <problem>`` line on stderr (equal problems of a split grouped
into one line); ``--strict`` makes it an error. Entries the layout does not know are ignored (one ``note:`` line
per split). A category's dataset card (``<category>_card.json``), where there is one, is read as training and
evaluation read it: a bad one is an error naming it, and a card whose camera (image size, focal length, camera
distance) disagrees with a split's files gets a warning (``--strict``: an error). Accepted formats and rules:
docs/data.md. A tqdm bar on
stderr shows progress when stderr is a terminal.

``--json PATH`` writes the same summary as JSON (a PATH that cannot be written, a folder or one under a file, is
refused before any split is read)::

    {"root": "<DIR>",
     "splits": [{"category", "split", "path", "objects", "views_min", "views_max", "views_total",
                 "resolution": [H, W] or null if mixed, "resolutions": [[H, W], ...],
                 "focal_min", "focal_max", "radius_min", "radius_max",
                 "has_depth", "has_mask", "has_mesh",                          # true if every object has it
                 "objects_with_depth", "objects_with_mask", "objects_with_mesh",     # usable ones
                 "skipped": ["<file>: <problem>", ...],
                 "rgb_formats": {"PNG 8-bit RGBA": views, ...},                     # counted over views
                 "depth_formats": {".npz" | ".npy" | "16-bit PNG": views, ...},    # usable depth only
                 "mask_formats": {"PNG 1-bit grey": views, ...},                   # usable masks only
                 "unusable": {"depth" | "mask" | "mesh": objects, ...},   # had the part, cannot use it
                 "warnings": ["<file>: <problem>; depth/ not used for this object", ...],
                 "ignored": {"meta.json": objects, "normal/": objects, ...}}, ...]}

Focal lengths are in pixels at the on-disk resolution; the camera radius is the norm of the pose translation.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import warnings
from pathlib import Path

from depthnerf.data.card import card_path, read_dataset_card
from depthnerf.data.srn import SPLITS, discover_categories, index_split, split_dir
from depthnerf.data.symmetry import plane_from_card
from depthnerf.data.synth.framing import dataset_framing
from depthnerf.data.validate import SplitSummary, card_camera_disagreements, summarize_split
from depthnerf.errors import DataWarning, DepthnerfError
from depthnerf.files import file_problem, write_text_atomic


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", type=Path, required=True, help="dataset root holding <category>_<split>/ folders")
    parser.add_argument("--json", type=Path, default=None, help="also write the summary as JSON to this file")
    parser.add_argument("--skip-bad", action="store_true", help="leave out bad objects and list them, not fail")
    parser.add_argument("--strict", action="store_true",
                        help="a problem in an optional part (depth/, mask/, mesh.ply) is an error, not a warning")
    parser.add_argument("--category", default=None, help="only this category (default: every one found)")
    parser.add_argument("--split", choices=SPLITS, default=None, help="only this split (default: every one found)")


def _range(low: float | None, high: float | None, digits: int) -> str:
    if low is None or high is None:
        return "?"
    a, b = f"{low:.{digits}f}", f"{high:.{digits}f}"
    return a if a == b or math.isclose(low, high) else f"{a}-{b}"


def _presence(count: int, total: int) -> str:
    return "all" if count == total else "none" if count == 0 else f"{count}/{total} objects"


def _formats(counts: dict[str, int]) -> str:
    return ", ".join(f"{name} ({n} views)" for name, n in counts.items())


def _part(count: int, total: int, unusable: int, formats: dict[str, int]) -> str:
    text = _presence(count, total)
    if formats:
        text += f"  [{_formats(formats)}]"
    return text + (f"  (unusable in {unusable} more objects, see warnings)" if unusable else "")


def format_summary(s: SplitSummary) -> list[str]:
    """The printed lines of one split's summary."""
    if s.resolution is not None:
        res = f"{s.resolution[0]}x{s.resolution[1]}"
    else:
        res = "mixed: " + ", ".join(f"{h}x{w}" for h, w in s.resolutions)
    lines = [
        f"{s.category}_{s.split}  ({s.path})",
        f"  objects        {s.objects}" + (f"  ({len(s.skipped)} skipped)" if s.skipped else ""),
        f"  views/object   {_range(s.views_min, s.views_max, 0)}  (total {s.views_total})",
        f"  resolution     {res}",
        f"  focal          {_range(s.focal_min, s.focal_max, 3)}",
        f"  camera radius  {_range(s.radius_min, s.radius_max, 3)}",
        f"  rgb            {_formats(s.rgb_formats) or '?'}",
        f"  depth          {_part(s.objects_with_depth, s.objects, s.unusable.get('depth', 0), s.depth_formats)}",
        f"  mask           {_part(s.objects_with_mask, s.objects, s.unusable.get('mask', 0), s.mask_formats)}",
        f"  mesh           {_part(s.objects_with_mesh, s.objects, s.unusable.get('mesh', 0), {})}",
        f"  warnings       {len(s.warnings)}" + ("  (listed on stderr; every one in --json)" if s.warnings else ""),
    ]
    if s.ignored:
        lines.append("  ignored        " + ", ".join(f"{name} ({n} objects)" for name, n in s.ignored.items()))
    lines += [f"  skipped: {line}" for line in s.skipped]
    return lines


def _check_card(root: Path, category: str) -> dict | None:
    """The category's dataset card, if it has one, read as training and evaluation read it (its pixel centre,
    framing and symmetry plane): a bad one is the error they would stop with."""
    card = read_dataset_card(root, category)
    if card is not None:
        where = str(card_path(root, category))
        dataset_framing(card, where)
        plane_from_card(card, where)
    return card


def _card_against_files(card: dict, where: str, summary: SplitSummary, strict: bool) -> SplitSummary:
    """``summary`` with a warning for each way the card's camera disagrees with the split's files (an error with
    ``strict``)."""
    lines = card_camera_disagreements(card, where, summary)
    if lines and strict:
        raise DepthnerfError(lines[0])
    for line in lines:
        warnings.warn(line, DataWarning, stacklevel=2)
    return dataclasses.replace(summary, warnings=[*summary.warnings, *lines])


def run(args: argparse.Namespace) -> int:
    root: Path = args.data
    if args.json is not None and (problem := file_problem(args.json, "--json")) is not None:
        raise DepthnerfError(problem)  # before the splits are read: the summary is written last
    categories = [args.category] if args.category else discover_categories(root)
    if not categories:
        raise DepthnerfError(f"{root}: no <category>_<split> folders (e.g. cars_train) found")
    summaries = []
    for category in categories:
        splits = [args.split] if args.split else [s for s in SPLITS if split_dir(root, category, s).is_dir()]
        if not splits:
            raise DepthnerfError(f"{root}: no {category}_<split> folders found")
        card = _check_card(root, category)
        for split in splits:
            index = index_split(root, category, split, skip_bad=args.skip_bad, check_files=True, progress=True,
                                strict=args.strict)
            summary = summarize_split(index)
            if card is not None:
                summary = _card_against_files(card, str(card_path(root, category)), summary, args.strict)
            print("\n".join(format_summary(summary)), flush=True)
            summaries.append(summary)
    if args.json is not None:
        payload = {"root": str(root), "splits": [dataclasses.asdict(s) for s in summaries]}
        try:
            write_text_atomic(args.json, json.dumps(payload, indent=2) + "\n")
        except OSError as err:
            raise DepthnerfError(f"{args.json}: cannot write JSON summary ({err.strerror or err})") from None
        print(f"wrote {args.json}")
    return 0
