"""Table-1 style Markdown from evaluation summaries (what ``depthnerf compare`` prints).

Input contract: ``summary.json`` written by ``depthnerf eval`` into its output directory, a JSON object with at
least ``psnr``, ``ssim`` (numbers), ``objects``, ``views`` (counts) and the provenance ``checkpoint_sha256``,
``preset``, ``category``, ``depth_prior``, ``method`` (the row label) and ``protocol`` (text); optional numbers
``chamfer_l1``, ``fscore`` (with optional ``fscore_tau``), ``floater_fraction`` and ``lpips`` (null = not
available), and optional counts ``empty_predictions`` / ``geometry_objects``: when predicted meshes were empty their
geometry cells read e.g. ``1.0000 (2/2 meshes empty)`` (worst-case values, not measured surfaces) and the
provenance line says so.

A path given to :func:`find_summaries` is a summary file, an eval output directory (``DIR/summary.json``) or a run
directory (``DIR/eval/*/summary.json``). Rows are methods (first-seen order), column groups are categories
(chairs, cars, then others alphabetically), each with PSNR and SSIM, plus Chamfer-L1 / F-score / Floaters / LPIPS
columns when some summary of that category has a non-null value; a missing cell is ``—``. Two summaries with the same
method and category are an error (they would share a cell).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from depthnerf.errors import DepthnerfError
from depthnerf.eval.config import RecordedChoices, recorded_choices

REQUIRED_KEYS = ("psnr", "ssim", "objects", "views", "checkpoint_sha256", "preset", "category", "depth_prior",
                 "method", "protocol")
"""Keys every ``summary.json`` must have."""
OPTIONAL_METRICS = ("chamfer_l1", "fscore", "floater_fraction", "lpips")
"""Optional metric keys (number or null)."""
METRIC_RANGES = {"psnr": (0.0, math.inf), "ssim": (-1.0, 1.0), "chamfer_l1": (0.0, math.inf), "fscore": (0.0, 1.0),
                 "floater_fraction": (0.0, 1.0), "lpips": (0.0, math.inf)}
"""The values each metric can take (inclusive): PSNR of images in [0, 1] is >= 0 (an error of at most 1 a pixel),
SSIM lies in [-1, 1], distances are >= 0, F-score and the floater share are fractions. A summary outside them was
not written by ``depthnerf eval``."""
PAPER_LABEL = "reported in the paper (real SRN)"
"""Suffix of the reference rows: numbers copied from the paper, measured on the real SRN data, not by us."""
PAPER_TABLE1 = (
    ("SRN", {"chairs": ("22.89", "0.89"), "cars": ("22.25", "0.88")}),
    ("pixelNeRF", {"chairs": ("23.72", "0.90"), "cars": ("23.17", "0.89")}),
    ("VisionNeRF", {"chairs": ("24.48", "0.92"), "cars": ("22.88", "0.90")}),
    ("Ours (depth-aware pixelNeRF)", {"chairs": ("24.26", "0.91"), "cars": ("23.50", "0.90")}),
)
"""The paper's Table 1: method -> category -> (PSNR, SSIM), as printed there (strings keep its precision)."""
CATEGORY_ORDER = ("chairs", "cars")
"""Column order of the paper; other categories follow alphabetically."""
COLUMNS = (("psnr", "PSNR", 2), ("ssim", "SSIM", 3), ("chamfer_l1", "CD-L1", 4), ("fscore", "F-score", 3),
           ("floater_fraction", "Floaters", 3), ("lpips", "LPIPS", 3))
"""(key, header, decimals) of every metric column, in order."""
MISSING = "—"
"""Cell text when a method has no value for a column."""
GEOMETRY_KEYS = ("chamfer_l1", "fscore", "floater_fraction")
"""Columns measured on the predicted meshes (marked when some were empty)."""
SAMPLE_KEYS = (("split", "splits"), ("views_stride", "--views-stride"), ("resolution", "--resolution"),
               ("input_views", "--input-views"))
"""``summary.json`` keys that say which views were scored and at which size, with how :func:`sample_warnings`
names a difference."""


@dataclass(frozen=True)
class EvalSummary:
    """One validated ``summary.json``."""

    path: Path
    """The file it was read from."""
    method: str
    """Row label."""
    category: str
    """Column group (lower case)."""
    metrics: dict[str, float | None]
    """``psnr``, ``ssim`` and the optional metrics present (None = reported unavailable)."""
    objects: int
    """Number of evaluated objects."""
    views: int
    """Number of evaluated views."""
    provenance: dict[str, str]
    """``checkpoint_sha256``, ``preset``, ``depth_prior``, ``protocol`` (and ``fscore_tau`` when given)."""
    choices: RecordedChoices | None = None
    """The protocol choices it was scored with (:func:`depthnerf.eval.config.recorded_choices`)."""
    empty_meshes: int = 0
    """Predicted meshes that were empty (``empty_predictions``: worst-case values in the geometry means)."""
    meshed_objects: int | None = None
    """Objects with geometry metrics (``geometry_objects``; None when the summary does not say)."""
    scoring: tuple[tuple[str, object], ...] = ()
    """The :data:`SAMPLE_KEYS` the summary records, with their values (which views, at which size)."""

    def empty_text(self) -> str:
        """``2/2 meshes empty`` when predicted meshes were empty, else ``""``."""
        if not self.empty_meshes:
            return ""
        of = f"/{self.meshed_objects}" if self.meshed_objects is not None else ""
        return f"{self.empty_meshes}{of} meshes empty"


def _number(path: Path, data: dict, key: str, optional: bool) -> float | None:
    value = data.get(key)
    if value is None and optional:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise DepthnerfError(f"{path}: '{key}' must be a finite number, got {value!r}")
    low, high = METRIC_RANGES[key]
    if not low <= value <= high:
        span = f">= {low:g}" if high == math.inf else f"within [{low:g}, {high:g}]"
        raise DepthnerfError(f"{path}: '{key}' is {value!r}, which no evaluation gives (it is {span})")
    return float(value)


def load_summary(path: Path) -> EvalSummary:
    """Read and check one ``summary.json``."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except OSError as err:
        raise DepthnerfError(f"{path}: cannot read summary ({err.strerror or err})") from None
    except json.JSONDecodeError as err:
        raise DepthnerfError(f"{path}: not valid JSON ({err.msg} at line {err.lineno})") from None
    except UnicodeDecodeError as err:
        raise DepthnerfError(f"{path}: not a JSON text file (byte {err.start} is not UTF-8)") from None
    if not isinstance(data, dict):
        raise DepthnerfError(f"{path}: summary must be a JSON object")
    missing = [k for k in REQUIRED_KEYS if k not in data]
    if missing:
        raise DepthnerfError(f"{path}: summary is missing {', '.join(missing)}")
    metrics = {k: _number(path, data, k, optional=False) for k in ("psnr", "ssim")}
    metrics.update({k: _number(path, data, k, optional=True) for k in OPTIONAL_METRICS if k in data})
    counts = {}
    for key in ("objects", "views"):
        if isinstance(data[key], bool) or not isinstance(data[key], int) or data[key] < 0:
            raise DepthnerfError(f"{path}: '{key}' must be a non-negative integer, got {data[key]!r}")
        counts[key] = data[key]
    for key in ("method", "category"):
        if not isinstance(data[key], str) or not data[key].strip():
            raise DepthnerfError(f"{path}: '{key}' must be a non-empty string, got {data[key]!r}")
    for key in ("empty_predictions", "geometry_objects"):
        value = data.get(key)
        if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 0):
            raise DepthnerfError(f"{path}: '{key}' must be a non-negative integer or null, got {value!r}")
    provenance = {k: str(data[k]) for k in ("checkpoint_sha256", "preset", "depth_prior", "protocol")}
    if data.get("fscore_tau") is not None:
        provenance["fscore_tau"] = str(data["fscore_tau"])
    return EvalSummary(path=path, method=data["method"].strip(), category=data["category"].strip().lower(),
                       metrics=metrics, objects=counts["objects"], views=counts["views"], provenance=provenance,
                       choices=recorded_choices(path, data), empty_meshes=data.get("empty_predictions") or 0,
                       meshed_objects=data.get("geometry_objects"),
                       scoring=tuple((k, data[k]) for k, _ in SAMPLE_KEYS if data.get(k) is not None))


def find_summaries(path: Path) -> list[Path]:
    """The summary files a command-line path stands for (file, eval out dir, or run dir)."""
    path = Path(path)
    if path.is_file():
        return [path]
    if not path.is_dir():
        raise DepthnerfError(f"{path}: no such file or directory")
    if (path / "summary.json").is_file():
        return [path / "summary.json"]
    found = sorted((path / "eval").glob("*/summary.json"))
    if not found:
        raise DepthnerfError(f"{path}: no summary.json here nor in {path / 'eval'}/*/ (run 'depthnerf eval' first)")
    return found


def sample_warnings(summaries: Sequence[EvalSummary]) -> list[str]:
    """One ``warning:`` line per category whose rows average different samples: other numbers of objects or views,
    other objects (the ids of ``per_object``), another split, ``--views-stride``, ``--resolution`` or
    ``--input-views`` (keys a summary does not record are not compared)."""
    lines = []
    for category in sorted({s.category for s in summaries}):
        rows = [s for s in summaries if s.category == category]
        parts = []
        sizes = sorted({(s.objects, s.views) for s in rows})
        if len(sizes) > 1:
            parts.append("on different samples (" + "; ".join(f"{o} objects x {v} views" for o, v in sizes) + ")")
        ids = {s.choices.scored_ids for s in rows if s.choices is not None and s.choices.scored_ids is not None}
        if len(sizes) == 1 and len(ids) > 1:
            parts.append("on different objects (as many in each)")
        for key, name in SAMPLE_KEYS:
            values = sorted({str(dict(s.scoring)[key]) for s in rows if key in dict(s.scoring)})
            if len(values) > 1:
                parts.append(f"with different {name} ({'; '.join(values)})")
        if parts:
            lines.append(f"warning: the {category} rows were scored {', '.join(parts)}: their means are not over "
                         "the same views")
    return lines


def _categories(summaries: Sequence[EvalSummary], reference: bool) -> list[str]:
    seen = {s.category for s in summaries} | (set(CATEGORY_ORDER) if reference else set())
    return [c for c in CATEGORY_ORDER if c in seen] + sorted(seen - set(CATEGORY_ORDER))


def _cell(text: str) -> str:
    """Text safe inside a Markdown table cell."""
    return text.replace("|", "\\|")


def _fmt(value: float | None, decimals: int) -> str:
    return MISSING if value is None else f"{value:.{decimals}f}"


def _metric_cell(s: EvalSummary, key: str, decimals: int) -> str:
    """A measured row's cell: the value, marked when it is a geometry figure and predicted meshes were empty."""
    value = s.metrics.get(key)
    text = _fmt(value, decimals)
    if value is not None and key in GEOMETRY_KEYS and s.empty_meshes:
        text += f" ({s.empty_text()})"
    return text


def markdown_table(summaries: Sequence[EvalSummary], reference: bool = False) -> str:
    """The Markdown table (with a provenance list under it) for the given summaries."""
    cells: dict[tuple[str, str], EvalSummary] = {}
    methods: list[str] = []
    for s in summaries:
        if (s.method, s.category) in cells:
            other = cells[(s.method, s.category)].path
            raise DepthnerfError(f"{s.path}: method '{s.method}' / category '{s.category}' is also given by {other}")
        cells[(s.method, s.category)] = s
        methods += [s.method] if s.method not in methods else []
    categories = _categories(summaries, reference)
    columns = []  # (category, key, header, decimals)
    for cat in categories:
        present = {k for s in summaries if s.category == cat for k, v in s.metrics.items() if v is not None}
        columns += [(cat, key, f"{cat.capitalize()} {head}", dec) for key, head, dec in COLUMNS
                    if key in ("psnr", "ssim") or key in present]
    lines = ["| Method | " + " | ".join(c[2] for c in columns) + " |",
             "|---|" + "---:|" * len(columns)]
    if reference:
        for name, values in PAPER_TABLE1:
            row = [values.get(cat, (MISSING, MISSING))[0 if key == "psnr" else 1]
                   if key in ("psnr", "ssim") else MISSING for cat, key, _, _ in columns]
            lines.append(f"| {name} — {PAPER_LABEL} | " + " | ".join(row) + " |")
    for method in methods:
        row = [_metric_cell(cells[(method, cat)], key, dec) if (method, cat) in cells else MISSING
               for cat, key, _, dec in columns]
        lines.append(f"| {_cell(method)} | " + " | ".join(row) + " |")
    if summaries:
        lines += ["", "Measured rows (this repository):"]
        for s in summaries:
            prov = s.provenance
            tau = f", F-score tau {prov['fscore_tau']}" if "fscore_tau" in prov else ""
            if s.empty_meshes:
                tau += (f"; {s.empty_text()}: their Chamfer-L1 / F-score are worst-case values, not measured "
                        "surfaces")
            lines.append(f"- {s.method} / {s.category}: {s.objects} objects, {s.views} views; preset "
                         f"{prov['preset']}, depth prior {prov['depth_prior']}, checkpoint "
                         f"{prov['checkpoint_sha256'][:12]}; protocol: {prov['protocol']}{tau} ({s.path})")
    if reference:
        lines += ["", f"Rows marked '{PAPER_LABEL}' are copied from the paper's Table 1 (ShapeNet SRN, "
                  "real data); they were not measured here."]
    return "\n".join(lines) + "\n"
