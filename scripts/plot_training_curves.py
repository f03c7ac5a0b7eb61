"""Validation PSNR against training step for study runs (the paper's Fig. 3: baseline vs depth-aware).

    python scripts/plot_training_curves.py --runs STUDY/runs/cars-none STUDY/runs/cars-bundled \\
        STUDY/runs/cars-oracle STUDY/runs/chairs-none ... --out STUDY/figures/training_curves.png

Input: run folders written by ``depthnerf train``. ``config.json`` gives the category (``data.category``: one
column of panels per category, chairs then cars then others, as in Table 1) and the depth prior
(``prior.estimator``: the line's label and colour). ``metrics.jsonl`` holds two kinds of records
(:mod:`depthnerf.train.run_log`, written by :mod:`depthnerf.train.loop`): training records (``step``, ``loss``,
``lr``, ...) every ``log.log_every`` steps and validation records (``step``, ``val_psnr``, ``val_ssim``) every
``log.val_every`` steps. A run without validation records is an error. Non-finite values (logged as null) are
left out; when a step is logged twice the last record wins; an unparseable *last* line (a record being written
by a live run) is ignored, an unparseable line elsewhere is an error.

Output: ``FIG.png`` (Agg backend): top row validation PSNR, bottom row training loss on a log scale (raw values
light, an exponential moving average of weight ``--smoothing`` solid, debiased as TensorBoard does), and
``FIG.csv`` beside it with every plotted number, one row per point: ``run,category,prior,label,metric,step,value``
with ``metric`` one of ``val_psnr``, ``loss``, ``loss_smoothed`` (values written with ``repr``, so they equal
the logged floats exactly).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from depthnerf.errors import DepthnerfError
from depthnerf.eval.table import CATEGORY_ORDER

PRIOR_ORDER = ("none", "bundled", "oracle", "depth-anything-v2")
"""Legend order of the depth priors (others follow alphabetically)."""
PRIOR_COLORS = {"none": "#4d4d4d", "bundled": "#1f77b4", "oracle": "#2ca02c", "depth-anything-v2": "#ff7f0e"}
"""Line colour per depth prior (others: matplotlib's default cycle)."""
CSV_COLUMNS = ("run", "category", "prior", "label", "metric", "step", "value")
"""Columns of ``FIG.csv``."""


def prior_label(estimator: str) -> str:
    """Legend label of a run trained with depth prior ``estimator``."""
    return "pixelNeRF (baseline)" if estimator == "none" else f"depth-aware ({estimator} prior)"


@dataclass(frozen=True)
class Series:
    """One plotted line: steps and values of equal length."""

    steps: tuple[int, ...]
    """Training steps, increasing."""
    values: tuple[float, ...]
    """Value at each step."""


@dataclass(frozen=True)
class RunCurves:
    """What is plotted for one run."""

    run: Path
    """The run folder."""
    category: str
    """``data.category`` of its config."""
    prior: str
    """``prior.estimator`` of its config."""
    label: str
    """Legend label."""
    val_psnr: Series
    """Validation PSNR (dB)."""
    loss: Series
    """Training loss (total, as logged)."""
    loss_smoothed: Series
    """:func:`ema` of ``loss``."""


def ema(values: Sequence[float], weight: float) -> list[float]:
    """Debiased exponential moving average: ``m_k = w m_{k-1} + (1 - w) x_k``, reported as ``m_k / (1 - w^k)``."""
    if not 0.0 <= weight < 1.0:
        raise DepthnerfError(f"--smoothing must be in [0, 1), got {weight}")
    out, mean = [], 0.0
    for k, x in enumerate(values, start=1):
        mean = weight * mean + (1.0 - weight) * x
        out.append(mean / (1.0 - weight**k))
    return out


def read_records(path: Path) -> list[dict]:
    """The JSON records of a ``metrics.jsonl`` (see the module docstring for the partial-last-line rule)."""
    try:
        lines = [line for line in path.read_text().splitlines() if line.strip()]
    except OSError as err:
        raise DepthnerfError(f"{path}: cannot read metrics ({err.strerror or err})") from None
    records = []
    for number, line in enumerate(lines, start=1):
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            if number == len(lines):
                break
            raise DepthnerfError(f"{path}: line {number} is not valid JSON") from None
        if not isinstance(record, dict) or not isinstance(record.get("step"), int):
            raise DepthnerfError(f"{path}: line {number} is not a metrics record with an integer 'step'")
        records.append(record)
    return records


def _series(records: Sequence[dict], key: str) -> Series:
    by_step: dict[int, float] = {}
    for record in records:
        value = record.get(key)
        if isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value):
            by_step[record["step"]] = float(value)
    steps = sorted(by_step)
    return Series(steps=tuple(steps), values=tuple(by_step[s] for s in steps))


def _config_field(config: dict, path: Path, section: str, key: str) -> str:
    value = config.get(section, {}).get(key) if isinstance(config.get(section), dict) else None
    if not isinstance(value, str) or not value:
        raise DepthnerfError(f"{path}: no '{section}.{key}' string (not a depthnerf run config)")
    return value


def read_run(run: Path, smoothing: float = 0.8) -> RunCurves:
    """Load one run folder's curves (errors name the file and the problem)."""
    run = Path(run)
    config_path, metrics_path = run / "config.json", run / "metrics.jsonl"
    if not config_path.is_file():
        raise DepthnerfError(f"{config_path}: missing (not a run folder of depthnerf train)")
    try:
        config = json.loads(config_path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise DepthnerfError(f"{config_path}: unreadable run config ({err})") from None
    if not isinstance(config, dict):
        raise DepthnerfError(f"{config_path}: run config must be a JSON object")
    category = _config_field(config, config_path, "data", "category")
    prior = _config_field(config, config_path, "prior", "estimator")
    if not metrics_path.is_file():
        raise DepthnerfError(f"{metrics_path}: missing (the run has not logged a step yet)")
    records = read_records(metrics_path)
    val_psnr = _series(records, "val_psnr")
    if not val_psnr.steps:
        raise DepthnerfError(f"{metrics_path}: no validation records (val_psnr); train with --log.val_every > 0")
    loss = _series(records, "loss")
    smoothed = Series(steps=loss.steps, values=tuple(ema(loss.values, smoothing)))
    return RunCurves(run=run, category=category, prior=prior, label=prior_label(prior), val_psnr=val_psnr,
                     loss=loss, loss_smoothed=smoothed)


def _unique_labels(curves: Sequence[RunCurves]) -> list[RunCurves]:
    """Runs sharing a category and prior get their folder name appended to the label."""
    seen: dict[tuple[str, str], int] = {}
    for c in curves:
        seen[(c.category, c.prior)] = seen.get((c.category, c.prior), 0) + 1
    return [c if seen[(c.category, c.prior)] == 1 else
            RunCurves(c.run, c.category, c.prior, f"{c.label} [{c.run.name}]", c.val_psnr, c.loss, c.loss_smoothed)
            for c in curves]


def ordered_categories(curves: Sequence[RunCurves]) -> list[str]:
    """Panel order: the Table-1 categories first (chairs, cars), then the others alphabetically."""
    seen = {c.category for c in curves}
    return [c for c in CATEGORY_ORDER if c in seen] + sorted(seen - set(CATEGORY_ORDER))


def _prior_rank(prior: str) -> tuple[int, str]:
    return (PRIOR_ORDER.index(prior) if prior in PRIOR_ORDER else len(PRIOR_ORDER), prior)


def csv_rows(curves: Sequence[RunCurves]) -> list[dict]:
    """Every plotted number as a ``FIG.csv`` row."""
    rows = []
    for c in curves:
        for metric, series in (("val_psnr", c.val_psnr), ("loss", c.loss), ("loss_smoothed", c.loss_smoothed)):
            rows += [{"run": str(c.run), "category": c.category, "prior": c.prior, "label": c.label,
                      "metric": metric, "step": step, "value": repr(value)}
                     for step, value in zip(series.steps, series.values, strict=True)]
    return rows


def plot(curves: Sequence[RunCurves], out: Path, title: str | None = None) -> None:
    """Draw the panels into ``out`` with the Agg backend (no pyplot state)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    categories = ordered_categories(curves)
    fig = Figure(figsize=(5.2 * len(categories), 6.2), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(2, len(categories), squeeze=False, sharex="col", gridspec_kw={"height_ratios": [3, 2]})
    for col, category in enumerate(categories):
        top, bottom = axes[0][col], axes[1][col]
        members = sorted((c for c in curves if c.category == category), key=lambda c: (_prior_rank(c.prior), c.label))
        for c in members:
            color = PRIOR_COLORS.get(c.prior)
            top.plot(c.val_psnr.steps, c.val_psnr.values, marker="o", markersize=3, color=color, label=c.label)
            line = bottom.plot(c.loss.steps, c.loss.values, color=color, alpha=0.2, linewidth=0.8)[0]
            bottom.plot(c.loss_smoothed.steps, c.loss_smoothed.values, color=line.get_color(), linewidth=1.4,
                        label=c.label)
        top.set_title(category)
        top.set_ylabel("validation PSNR (dB)")
        top.grid(alpha=0.3)
        top.legend(fontsize=8, loc="best")
        bottom.set_xlabel("training step")
        bottom.set_ylabel("training loss (smoothed)")
        if any(v > 0 for c in members for v in c.loss.values):
            bottom.set_yscale("log")
        bottom.grid(alpha=0.3, which="both")
    if title:
        fig.suptitle(title)
    fig.savefig(out, dpi=150)


def write_csv(path: Path, rows: Sequence[dict]) -> None:
    """Write ``rows`` with :data:`CSV_COLUMNS`."""
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(CSV_COLUMNS))
        writer.writeheader()
        writer.writerows(rows)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", nargs="+", type=Path, required=True, metavar="RUN", help="run folders")
    parser.add_argument("--out", type=Path, required=True, help="figure file (FIG.png); FIG.csv is written beside it")
    parser.add_argument("--title", default=None, help="figure title")
    parser.add_argument("--smoothing", type=float, default=0.8, help="EMA weight of the loss curve (default 0.8)")
    args = parser.parse_args(argv)
    try:
        if args.out.suffix.lower() == ".csv":
            raise DepthnerfError(f"{args.out}: --out is the figure; its numbers go to the .csv beside it")
        curves = _unique_labels([read_run(run, args.smoothing) for run in args.runs])
        args.out.parent.mkdir(parents=True, exist_ok=True)
        plot(curves, args.out, args.title)
        csv_path = args.out.with_suffix(".csv")
        write_csv(csv_path, csv_rows(curves))
    except DepthnerfError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"wrote {args.out} and {csv_path} ({len(curves)} runs)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
