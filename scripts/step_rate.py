"""The median ms per training step of a run, over the second half of its logged steps (``metrics.jsonl``), each
step's rays taken from the run's ``config.json`` (phase 1's objects before ``schedule.bbox_steps``, phase 2's after;
the logged step ``k`` ran step index ``k - 1``). The lease scripts' step-rate figure.

    python scripts/step_rate.py RUN_DIR        # prints the figure (nothing when no step was timed)
"""

from __future__ import annotations

import json
import statistics
import sys
from pathlib import Path


def log_rows(path: Path) -> list[dict]:
    """The JSON lines of a run's log; a cut-off last line (a run killed while writing it) is left out, and any
    other line that is not a JSON object is a one-line error naming the file and the line."""
    lines = path.read_text().splitlines()
    rows = []
    for number, line in enumerate(lines, start=1):
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            if number == len(lines):
                break
            raise SystemExit(f"error: {path}: line {number} is not JSON") from None
        if not isinstance(row, dict):
            raise SystemExit(f"error: {path}: line {number} is not a JSON object")
        rows.append(row)
    return rows


def ms_per_step(run_dir: Path) -> float | None:
    """The figure of the module docstring; None without a config, a log or a timed step."""
    run_dir = Path(run_dir)
    if not (run_dir / "config.json").is_file() or not (run_dir / "metrics.jsonl").is_file():
        return None
    sched = json.loads((run_dir / "config.json").read_text())["schedule"]
    rows = log_rows(run_dir / "metrics.jsonl")
    timed = [r for r in rows if "loss" in r and r.get("rays_per_s")]

    def rays(step: int) -> int:
        return sched["rays_per_object"] * sched["objects_phase1" if step - 1 < sched["bbox_steps"] else "objects_phase2"]

    ms = [1e3 * rays(r["step"]) / r["rays_per_s"] for r in timed[len(timed) // 2:]]
    return statistics.median(ms) if ms else None


if __name__ == "__main__":
    value = ms_per_step(Path(sys.argv[1]))
    if value is not None:
        print(f"{value:.3f}")
