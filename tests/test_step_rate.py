"""scripts/step_rate.py: the median ms per step over the second half of a run's timed steps, by hand."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from fixtures_scripts import load_script

from depthnerf.errors import DepthnerfError


def _run(tmp_path: Path, rows: list[dict], tail: str = "") -> Path:
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"schedule": {"rays_per_object": 128, "objects_phase1": 4,
                                                              "objects_phase2": 2, "bbox_steps": 2}}))
    (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows) + tail)
    return run


def test_the_median_of_the_second_half_with_each_phases_rays(tmp_path):
    rows = [{"step": 1, "loss": 1.0, "rays_per_s": 512 * 10.0},   # phase 1 (step index 0 < bbox_steps): 512 rays
            {"step": 2, "loss": 1.0, "rays_per_s": 512 * 20.0},
            {"step": 3, "loss": 1.0, "rays_per_s": 256 * 40.0},   # phase 2: 256 rays, 25 ms
            {"step": 3, "val_psnr": 20.0},
            {"step": 4, "loss": 1.0, "rays_per_s": 256 / 0.030}]  # 30 ms
    mod = load_script("step_rate")
    assert mod.ms_per_step(_run(tmp_path, rows)) == pytest.approx(27.5)  # median of the last two of four


def test_a_cut_off_last_line_is_left_out_and_a_bad_line_before_it_is_one_error(tmp_path):
    rows = [{"step": 1, "loss": 1.0, "rays_per_s": 512 * 10.0}, {"step": 2, "loss": 1.0, "rays_per_s": 512 * 20.0}]
    mod = load_script("step_rate")
    run = _run(tmp_path, rows, tail='{"step": 3, "lo')
    assert mod.ms_per_step(run) == pytest.approx(50.0)
    (run / "metrics.jsonl").write_text('{"step": 1, "lo\n' + json.dumps(rows[1]) + "\n")
    with pytest.raises(DepthnerfError, match=r"metrics.jsonl: line 1 is not valid JSON"):
        mod.ms_per_step(run)
