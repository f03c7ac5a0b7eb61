"""Paired per-object differences between evaluations of the same test objects (docs/RESULTS.md).

A mean PSNR over 50 objects moves by a few tenths of a dB with the choice of objects; two methods scored on the
SAME objects are compared far more precisely by the per-object differences. For each ``--method`` eval folder
against the ``--baseline`` one (both written by ``depthnerf eval``; their ``per_object.csv`` files must list the
same objects, each with the same input view and number of scored views, and their ``summary.json`` files the same
category, split, ``--views-stride``, ``--resolution``, ``--ssim`` and ``--scored``: evaluations scored on other
views or another way are refused in one line; ``--common-views`` instead pairs PSNR and SSIM over the target
views both scored, e.g. one input view against two, ``depthnerf eval --input-views 64 104``), this prints, per
metric, the mean difference (method - baseline), its standard error ``std(d, ddof=1) / sqrt(n)``, a 95% interval
``mean +- t_{0.975, n-1} * SE`` and how many objects the method wins.

    python scripts/paired_difference.py --baseline study/eval/cars-none \
        --method study/eval/cars-bundled study/eval/cars-oracle [--json OUT.json]
    python scripts/paired_difference.py --baseline eval/one-view --method eval/two-views --common-views
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

from scipy import stats

from depthnerf.data.protocol import protocol_views
from depthnerf.errors import DepthnerfError
from depthnerf.eval.config import protocol_mismatch, recorded_choices

METRICS: dict[str, bool] = {"psnr": True, "ssim": True, "chamfer_l1": False, "fscore": True,
                             "accuracy": False, "completeness": False, "floater_fraction": False}
"""Metric column of per_object.csv -> whether higher is better (accuracy and completeness: the two halves of
Chamfer-L1, mesh to truth and truth to mesh; a column an evaluation lacks is skipped)."""
SCORING_KEYS = {"category": "category", "split": "--split", "views_stride": "--views-stride",
                "resolution": "--resolution"}
"""``summary.json`` keys two paired evaluations must share (the same views, scored at the same size), with the
``depthnerf eval`` option that sets each."""


@dataclass
class PairedStat:
    """One metric of one method against the baseline, over the objects both scored."""

    method: str
    metric: str
    n: int
    baseline_mean: float
    method_mean: float
    mean_diff: float
    std_err: float
    ci95_low: float
    ci95_high: float
    wins: int
    no_worse: int = 0
    """Objects on which the method is at least as good as the baseline (ties count: floater fractions are often
    exactly 0 for both)."""


def t_interval(diffs: list[float]) -> tuple[float, float, float]:
    """(mean, standard error, half-width of the 95% t-interval) of paired differences; the last two are NaN for
    fewer than 2 differences, all three for none."""
    n = len(diffs)
    mean = sum(diffs) / n if n else float("nan")
    if n < 2:
        return mean, float("nan"), float("nan")
    se = math.sqrt(sum((x - mean) ** 2 for x in diffs) / (n - 1) / n)
    return mean, se, float(stats.t.ppf(0.975, n - 1)) * se


def read_per_object(folder: Path) -> dict[str, dict[str, str]]:
    """Rows of ``folder/per_object.csv`` keyed by object id; a one-line error names the file when it is missing or
    unreadable, lacks the ``object_id`` column, lists an object twice or has a :data:`METRICS` cell that is neither
    empty nor a finite number."""
    path = folder / "per_object.csv"
    if not path.is_file():
        raise SystemExit(f"error: {path}: missing (run depthnerf eval with --out {folder})")
    try:
        with open(path, newline="", encoding="utf-8") as f:
            reader = csv.DictReader(f)
            rows = list(reader)
            columns = reader.fieldnames or []
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise SystemExit(f"error: {path}: unreadable ({err})") from None
    if "object_id" not in columns:
        raise SystemExit(f"error: {path}: no object_id column (not a per_object.csv of depthnerf eval)")
    out: dict[str, dict[str, str]] = {}
    for row in rows:
        oid = row["object_id"]
        if oid in out:
            raise SystemExit(f"error: {path}: object {oid} is listed twice")
        for metric in METRICS:
            text = row.get(metric)
            if text and not _finite(text):
                raise SystemExit(f"error: {path}: object {oid}: {metric} {text!r} is not a finite number")
        out[oid] = row
    return out


def _finite(text: str) -> bool:
    try:
        return math.isfinite(float(text))
    except ValueError:
        return False


def same_views(a: dict[str, str], b: dict[str, str]) -> bool:
    """Whether two ``per_object.csv`` rows of an object were scored on the same views: the same number of target
    views, primary input view and input views (``input_views``, else ``input_view`` in a file without it)."""
    inputs = [row.get("input_views") or row.get("input_view") for row in (a, b)]
    return all(a.get(k) == b.get(k) for k in ("views", "input_view")) and inputs[0] == inputs[1]


def read_summary(folder: Path) -> dict:
    """``folder/summary.json`` as a mapping; empty when the folder has none (an error names it if unreadable)."""
    path = folder / "summary.json"
    if not path.is_file():
        return {}
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as err:  # ValueError: not JSON, or not UTF-8 text
        raise SystemExit(f"error: {path}: unreadable ({err})") from None
    return data if isinstance(data, dict) else {}


def scoring_difference(baseline: Path, base: dict, method: Path, other: dict) -> str | None:
    """One line saying how the evaluation in ``method`` (its ``summary.json`` mapping ``other``) was scored
    differently from the one in ``baseline`` (``base``): other views, split or size (:data:`SCORING_KEYS`) or other
    protocol choices (:func:`depthnerf.eval.config.protocol_mismatch`); None when they agree. A key either summary
    lacks (an older summary) is not compared."""
    for key, flag in SCORING_KEYS.items():
        if key in base and key in other and base[key] != other[key]:
            return (f"{method / 'summary.json'} was scored with {flag} {other[key]} but {baseline / 'summary.json'} "
                    f"with {flag} {base[key]}")
    return protocol_mismatch([recorded_choices(baseline / "summary.json", base),
                              recorded_choices(method / "summary.json", other)])


def pairing_refusal(baseline: Path, base: dict, method: Path, other: dict) -> str | None:
    """The one-line refusal to pair two evaluations scored differently (:func:`scoring_difference`), else None."""
    difference = scoring_difference(baseline, base, method, other)
    if difference is None:
        return None
    return (f"{difference}: not the same views scored the same way, so not paired (evaluate both with the same "
            "options)")


def check_pairable(baseline: Path, method: Path) -> None:
    """A one-line ``SystemExit`` when the two evaluations were scored differently (:func:`pairing_refusal`)."""
    try:
        refusal = pairing_refusal(baseline, read_summary(baseline), method, read_summary(method))
    except DepthnerfError as err:
        raise SystemExit(f"error: {err}") from None
    if refusal is not None:
        raise SystemExit(f"error: {refusal}")


def method_name(folder: Path) -> str:
    """The method label recorded in the eval summary, else the folder name."""
    return str(read_summary(folder).get("method", folder.name))


def scored_views(folder: Path, summary: dict, object_id: str) -> dict[int, dict]:
    """Target view -> its metrics (``psnr``, ``ssim``) of one object of the evaluation in ``folder``, from its
    result file (``objects/<id>.json``), the views named by the protocol of its ``summary.json`` mapping
    ``summary`` (the object's view count read from its ``rgb/`` folder in the data the summary names)."""
    path = folder / "objects" / f"{object_id}.json"
    try:
        views = json.loads(path.read_text(encoding="utf-8"))["metrics"]["views"]
        rgb = Path(summary["data_card"]["root"]) / f"{summary['category']}_{summary['split']}" / object_id / "rgb"
        inputs = summary.get("input_views")
        count = sum(1 for f in rgb.iterdir() if f.suffix.lower() == ".png")
        targets = protocol_views(count, summary["views_stride"],
                                 inputs if inputs and isinstance(inputs[0], int) else None).targets
    except (OSError, ValueError, KeyError, TypeError, DepthnerfError) as err:
        raise SystemExit(f"error: {path}: cannot tell which views it scored ({err})") from None
    if len(targets) != len(views):
        raise SystemExit(f"error: {path}: {len(views)} scored views, but its protocol names {len(targets)}")
    return dict(zip(targets, views, strict=True))


def common_view_rows(baseline: Path, method: Path, base: dict, other: dict) -> int:
    """Set both evaluations' per-object PSNR and SSIM (rows ``base``, ``other`` of their ``per_object.csv``) to
    their means over the target views both scored (the per-view mean, as ``depthnerf eval``'s own; the mesh metrics
    do not depend on the targets); return how many views that is per object (the fewest). Each shared view's own
    PSNR difference (method - baseline, mean +- standard error over the objects that scored it) goes to stderr."""
    fewest, summaries = None, (read_summary(baseline), read_summary(method))
    by_view: dict[int, list[float]] = {}
    for oid in sorted(set(base) & set(other)):
        a, b = scored_views(baseline, summaries[0], oid), scored_views(method, summaries[1], oid)
        shared = sorted(set(a) & set(b))
        if not shared:
            raise SystemExit(f"error: object {oid}: {baseline} and {method} scored no view in common")
        fewest = len(shared) if fewest is None else min(fewest, len(shared))
        for rows, views in ((base, a), (other, b)):
            rows[oid].update({k: repr(sum(views[v][k] for v in shared) / len(shared)) for k in ("psnr", "ssim")})
        for v in shared:
            by_view.setdefault(v, []).append(b[v]["psnr"] - a[v]["psnr"])
    for v, diffs in sorted(by_view.items()):
        mean, se, _ = t_interval(diffs)
        print(f"view {v}: PSNR {mean:+.2f} +- {se:.2f} dB over {len(diffs)} objects", file=sys.stderr)
    return fewest or 0


def paired(baseline: Path, method: Path, common: bool = False, common_views: bool = False) -> list[PairedStat]:
    """Paired statistics of ``method`` against ``baseline`` for every metric both have (``common``: on the objects
    both scored, e.g. an evaluation stopped early, instead of requiring the same objects; ``common_views``: PSNR and
    SSIM over the target views both scored, whatever their input views, :func:`common_view_rows`)."""
    base, other = read_per_object(baseline), read_per_object(method)
    check_pairable(baseline, method)
    if common:
        shared = set(base) & set(other)
        base, other = {k: base[k] for k in shared}, {k: other[k] for k in shared}
    if set(base) != set(other):
        raise SystemExit(f"error: {method}/per_object.csv: objects differ from {baseline}/per_object.csv "
                         "(--common pairs the objects both scored)")
    if common_views:
        fewest = common_view_rows(baseline, method, base, other)
        print(f"pairing {method} on the target views both scored: at least {fewest} per object", file=sys.stderr)
    else:
        for oid in base:
            if not same_views(base[oid], other[oid]):
                raise SystemExit(f"error: {method}/per_object.csv: object {oid} was scored on other views than "
                                 f"in {baseline} (--common-views pairs the views both scored)")
    out = []
    for metric, higher in METRICS.items():
        ids = [o for o in sorted(base) if base[o].get(metric) and other[o].get(metric)]
        if len(ids) < 2:
            continue
        b = [float(base[o][metric]) for o in ids]
        m = [float(other[o][metric]) for o in ids]
        d = [x - y for x, y in zip(m, b, strict=True)]
        n = len(d)
        mean, se, half = t_interval(d)
        wins = sum(1 for x in d if (x > 0 if higher else x < 0))
        no_worse = sum(1 for x in d if (x >= 0 if higher else x <= 0))
        out.append(PairedStat(method=method_name(method), metric=metric, n=n, baseline_mean=sum(b) / n,
                              method_mean=sum(m) / n, mean_diff=mean, std_err=se, ci95_low=mean - half,
                              ci95_high=mean + half, wins=wins, no_worse=no_worse))
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", type=Path, required=True, help="eval folder of the baseline")
    parser.add_argument("--method", type=Path, nargs="+", required=True, help="eval folders to compare")
    parser.add_argument("--json", type=Path, help="also write the rows as JSON")
    parser.add_argument("--common", action="store_true",
                        help="pair on the objects both evaluations scored (default: they must be the same)")
    parser.add_argument("--common-views", action="store_true",
                        help="pair PSNR and SSIM over the target views both scored (e.g. other --input-views)")
    args = parser.parse_args(argv)
    rows = [s for folder in args.method for s in paired(args.baseline, folder, args.common, args.common_views)]
    print(f"paired against {method_name(args.baseline)} ({args.baseline})")
    print("| method | metric | objects | baseline | method | difference | 95% interval | wins | no worse |")
    print("|---|---|---|---|---|---|---|---|---|")
    for s in rows:
        dec = 2 if s.metric == "psnr" else 4
        print(f"| {s.method} | {s.metric} | {s.n} | {s.baseline_mean:.{dec}f} | {s.method_mean:.{dec}f} | "
              f"{s.mean_diff:+.{dec}f} +- {s.std_err:.{dec}f} | [{s.ci95_low:+.{dec}f}, {s.ci95_high:+.{dec}f}] | "
              f"{s.wins}/{s.n} | {s.no_worse}/{s.n} |")
    if args.json:
        args.json.write_text(json.dumps([asdict(s) for s in rows], indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
