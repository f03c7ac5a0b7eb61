"""scripts/seed_paired_difference.py against hand-computed statistics and a brute-force Welch interval."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import pytest
from fixtures_scripts import load_script
from scipy import stats

spd = load_script("seed_paired_difference")


def _write(folder: Path, psnr: list[float], chamfer: list[float], views: str = "10") -> Path:
    folder.mkdir(parents=True)
    (folder / "summary.json").write_text(json.dumps({"method": folder.name}))
    with open(folder / "per_object.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["object_id", "views", "psnr", "chamfer_l1"])
        w.writeheader()
        for k, (p, c) in enumerate(zip(psnr, chamfer, strict=True)):
            w.writerow({"object_id": f"obj{k}", "views": views, "psnr": p, "chamfer_l1": c})
    return folder


def test_seed_averages_pairings_and_run_level(tmp_path: Path) -> None:
    b0 = _write(tmp_path / "b0", [20.0, 22.0, 18.0], [0.10, 0.20, 0.30])
    b1 = _write(tmp_path / "b1", [21.0, 23.0, 19.0], [0.10, 0.20, 0.30])
    m0 = _write(tmp_path / "m0", [21.0, 22.0, 20.0], [0.05, 0.25, 0.30])
    m1 = _write(tmp_path / "m1", [22.5, 23.5, 20.5], [0.05, 0.15, 0.20])
    rows = {s.metric: s for s in spd.seed_paired([b0, b1], [m0, m1])}
    s = rows["psnr"]
    # seed means per object: baseline 20.5, 22.5, 18.5; method 21.75, 22.75, 20.25 -> diffs 1.25, 0.25, 1.75
    d = [1.25, 0.25, 1.75]
    mean = sum(d) / 3
    half = stats.t.ppf(0.975, 2) * math.sqrt(sum((x - mean) ** 2 for x in d) / 2 / 3)
    assert s.averaged_diff == pytest.approx(mean)
    assert s.averaged_ci95 == pytest.approx((mean - half, mean + half))
    assert s.averaged_no_worse == 3 and (s.baseline_seeds, s.method_seeds, s.objects) == (2, 2, 3)
    # pairings, method-major: (m0,b0) (m0,b1) (m1,b0) (m1,b1)
    assert s.pairing_diffs == pytest.approx([1.0, 0.0, 6.5 / 3, 3.5 / 3])
    # run means: baseline 20, 21; method 21, 22.1667
    runs_b, runs_m = [20.0, 21.0], [21.0, 66.5 / 3]
    assert (s.baseline_spread, s.method_spread) == pytest.approx((1.0, 66.5 / 3 - 21.0))
    va, vb = (runs_m[0] - runs_m[1]) ** 2 / 2 / 2, (runs_b[0] - runs_b[1]) ** 2 / 2 / 2
    dof = (va + vb) ** 2 / (va ** 2 + vb ** 2)
    diff = sum(runs_m) / 2 - sum(runs_b) / 2
    w = stats.t.ppf(0.975, dof) * math.sqrt(va + vb)
    assert s.run_ci95 == pytest.approx((diff - w, diff + w))
    c = rows["chamfer_l1"]  # lower is better
    assert c.averaged_no_worse == 3 and c.averaged_diff < 0


def test_pairings_better_counts_intervals_on_the_better_side(tmp_path: Path) -> None:
    b = _write(tmp_path / "b", [20.0, 21.0, 22.0, 23.0], [0.1, 0.1, 0.1, 0.1])
    better = _write(tmp_path / "m", [21.0, 22.1, 22.9, 24.0], [0.2, 0.2, 0.2, 0.2])
    rows = {s.metric: s for s in spd.seed_paired([b], [better])}
    assert rows["psnr"].pairings_better == 1 and rows["psnr"].run_ci95 is None
    assert rows["chamfer_l1"].pairings_better == 0 and rows["chamfer_l1"].averaged_no_worse == 0


def test_mismatched_objects_name_the_file(tmp_path: Path) -> None:
    b0 = _write(tmp_path / "b0", [20.0, 22.0], [0.1, 0.2])
    b1 = _write(tmp_path / "b1", [20.0, 22.0, 23.0], [0.1, 0.2, 0.3])
    m = _write(tmp_path / "m", [20.0, 22.0], [0.1, 0.2], views="5")
    with pytest.raises(SystemExit, match="b1/per_object.csv"):
        spd.seed_paired([b0, b1], [m])
    with pytest.raises(SystemExit, match="m/per_object.csv"):
        spd.seed_paired([b0], [m])


def test_seeds_scored_at_another_resolution_are_refused(tmp_path: Path) -> None:
    b0 = _write(tmp_path / "b0", [20.0, 22.0, 18.0], [0.10, 0.20, 0.30])
    m0 = _write(tmp_path / "m0", [21.0, 22.0, 20.0], [0.05, 0.25, 0.30])
    for folder, res in ((b0, 64), (m0, 128)):
        (folder / "summary.json").write_text(json.dumps({"method": folder.name, "resolution": res}))
    with pytest.raises(SystemExit, match="--resolution 128 but .* not paired"):
        spd.seed_paired([b0], [m0])


def test_seeds_conditioned_on_other_input_views_are_refused(tmp_path: Path) -> None:
    """One input view against two (``input_views`` 64 against 64 104) with as many targets scored: the same
    ``input_view`` and ``views`` are not the same views, as in paired_difference.py."""
    b0 = _write(tmp_path / "b0", [20.0, 22.0, 18.0], [0.10, 0.20, 0.30])
    m0 = _write(tmp_path / "m0", [21.0, 22.0, 20.0], [0.05, 0.25, 0.30])
    for folder, inputs in ((b0, "64"), (m0, "64 104")):
        with open(folder / "per_object.csv", newline="") as f:
            rows = list(csv.DictReader(f))
        with open(folder / "per_object.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=[*rows[0], "input_view", "input_views"])
            w.writeheader()
            w.writerows({**r, "input_view": "64", "input_views": inputs} for r in rows)
    with pytest.raises(SystemExit, match="m0/per_object.csv: objects or views differ"):
        spd.seed_paired([b0], [m0])
