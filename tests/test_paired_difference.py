"""scripts/paired_difference.py against hand-computed paired statistics."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import pytest
from fixtures_scripts import load_script
from scipy import stats


def _load():
    return load_script("paired_difference")


def _write(folder: Path, method: str, psnr: list[float], chamfer: list[float], views: str = "10") -> Path:
    folder.mkdir(parents=True)
    (folder / "summary.json").write_text(json.dumps({"method": method}))
    with open(folder / "per_object.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["object_id", "views", "psnr", "ssim", "chamfer_l1", "fscore"])
        w.writeheader()
        for k, (p, c) in enumerate(zip(psnr, chamfer, strict=True)):
            w.writerow({"object_id": f"obj{k}", "views": views, "psnr": p, "ssim": "", "chamfer_l1": c,
                        "fscore": ""})
    return folder


def test_paired_statistics_match_hand_computation(tmp_path: Path) -> None:
    pd = _load()
    base = _write(tmp_path / "base", "baseline", [20.0, 22.0, 18.0, 25.0], [0.10, 0.20, 0.30, 0.40])
    meth = _write(tmp_path / "meth", "depth", [21.0, 22.5, 17.0, 27.0], [0.05, 0.25, 0.10, 0.30])
    rows = {s.metric: s for s in pd.paired(base, meth)}
    assert set(rows) == {"psnr", "chamfer_l1"}  # empty columns are skipped
    d = [1.0, 0.5, -1.0, 2.0]
    mean = sum(d) / 4
    se = math.sqrt(sum((x - mean) ** 2 for x in d) / 3 / 4)
    s = rows["psnr"]
    assert s.method == "depth" and s.n == 4 and s.wins == 3
    assert s.mean_diff == pytest.approx(0.625) and s.std_err == pytest.approx(se)
    assert s.ci95_high - s.mean_diff == pytest.approx(stats.t.ppf(0.975, 3) * se)
    assert s.baseline_mean == pytest.approx(21.25) and s.method_mean == pytest.approx(21.875)
    assert rows["chamfer_l1"].wins == 3  # lower is better: 0.05<0.10, 0.10<0.30, 0.30<0.40
    assert s.no_worse == 3 and rows["chamfer_l1"].no_worse == 3


def test_ties_count_as_no_worse(tmp_path: Path) -> None:
    pd = _load()
    base = _write(tmp_path / "base", "baseline", [20.0, 22.0, 18.0], [0.10, 0.20, 0.30])
    meth = _write(tmp_path / "meth", "depth", [20.0, 21.0, 19.0], [0.10, 0.25, 0.30])
    rows = {s.metric: s for s in pd.paired(base, meth)}
    assert (rows["psnr"].wins, rows["psnr"].no_worse) == (1, 2)
    assert (rows["chamfer_l1"].wins, rows["chamfer_l1"].no_worse) == (0, 2)


def test_mismatched_objects_or_views_are_errors(tmp_path: Path) -> None:
    pd = _load()
    base = _write(tmp_path / "base", "baseline", [20.0, 22.0], [0.1, 0.2])
    fewer = _write(tmp_path / "fewer", "depth", [20.0], [0.1])
    with pytest.raises(SystemExit, match="objects differ"):
        pd.paired(base, fewer)
    other_views = _write(tmp_path / "views", "depth", [20.0, 22.0], [0.1, 0.2], views="25")
    with pytest.raises(SystemExit, match="other views"):
        pd.paired(base, other_views)
    with pytest.raises(SystemExit, match="per_object.csv: missing"):
        pd.paired(base, tmp_path / "nowhere")
