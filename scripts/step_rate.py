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

from plot_training_curves import read_records

from depthnerf.errors import DepthnerfError


def ms_per_step(run_dir: Path) -> float | None:
    """The figure of the module docstring; None without a config, a log or a timed step."""
    run_dir = Path(run_dir)
    if not (run_dir / "config.json").is_file() or not (run_dir / "metrics.jsonl").is_file():
        return None
    sched = json.loads((run_dir / "config.json").read_text())["schedule"]
    rows = read_records(run_dir / "metrics.jsonl")  # a cut-off last line left out, any other bad line an error
    timed = [r for r in rows if "loss" in r and r.get("rays_per_s")]

    def rays(step: int) -> int:
        return sched["rays_per_object"] * sched["objects_phase1" if step - 1 < sched["bbox_steps"] else "objects_phase2"]

    ms = [1e3 * rays(r["step"]) / r["rays_per_s"] for r in timed[len(timed) // 2:]]
    return statistics.median(ms) if ms else None


if __name__ == "__main__":
    try:
        value = ms_per_step(Path(sys.argv[1]))
    except DepthnerfError as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)
    if value is not None:
        print(f"{value:.3f}")
