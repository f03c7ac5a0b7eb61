"""``depthnerf inspect``: summary, --json content, bad input through the CLI (exit 2, file named), --skip-bad."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from fixtures_srn import BAD_INPUT_CASES, make_srn_fixture

from depthnerf.cli import main


def test_inspect_json_content(srn_root_full: Path, tmp_path: Path, capsys):
    make_srn_fixture(srn_root_full, category="chairs", splits={"train": 1}, views=2, size=8)
    out_json = tmp_path / "summary.json"
    assert main(["inspect", "--data", str(srn_root_full), "--json", str(out_json)]) == 0
    printed = capsys.readouterr().out
    summary = json.loads(out_json.read_text())
    assert summary["root"] == str(srn_root_full)
    assert [(s["category"], s["split"]) for s in summary["splits"]] == [
        ("cars", "train"), ("cars", "val"), ("cars", "test"), ("chairs", "train")]
    cars_train, chairs = summary["splits"][0], summary["splits"][3]
    assert cars_train["objects"] == 2 and cars_train["views_min"] == cars_train["views_max"] == 3
    assert cars_train["views_total"] == 6 and cars_train["resolution"] == [16, 16]
    assert cars_train["focal_min"] == cars_train["focal_max"] == 131.25 * 16 / 128
    assert cars_train["radius_min"] == pytest.approx(1.3, abs=1e-6)
    assert cars_train["radius_max"] == pytest.approx(1.3, abs=1e-6)
    assert cars_train["has_depth"] and cars_train["has_mask"] and cars_train["has_mesh"]
    assert cars_train["objects_with_mesh"] == 2 and cars_train["skipped"] == []
    assert chairs["path"].endswith("chairs_train/chairs_2.0_train") and chairs["resolution"] == [8, 8]
    assert chairs["radius_max"] == pytest.approx(2.0, abs=1e-6) and not chairs["has_depth"]
    assert chairs["objects_with_depth"] == 0
    assert "cars_val" in printed and "camera radius  1.300" in printed and "focal          16.406" in printed
    assert "mesh           all" in printed and "depth          none" in printed


def test_inspect_category_and_split_filters(srn_root_full: Path, tmp_path: Path, capsys):
    out_json = tmp_path / "s.json"
    assert main(["inspect", "--data", str(srn_root_full), "--category", "cars", "--split", "val",
                 "--json", str(out_json)]) == 0
    assert [s["split"] for s in json.loads(out_json.read_text())["splits"]] == ["val"]
    assert main(["inspect", "--data", str(srn_root_full), "--category", "planes"]) == 2
    assert "no planes_<split> folders" in capsys.readouterr().err
    assert main(["inspect", "--data", str(tmp_path / "missing")]) == 2
    assert "dataset folder does not exist" in capsys.readouterr().err


def test_inspect_mixed_resolutions(tmp_path: Path, capsys):
    make_srn_fixture(tmp_path, splits={"train": 1}, size=16)
    (tmp_path / "cars_train").rename(tmp_path / "a")
    make_srn_fixture(tmp_path, splits={"train": 1}, size=8)
    for obj in (tmp_path / "a").iterdir():
        obj.rename(tmp_path / "cars_train" / (obj.name + "x"))
    out_json = tmp_path / "s.json"
    assert main(["inspect", "--data", str(tmp_path), "--json", str(out_json)]) == 0
    split = json.loads(out_json.read_text())["splits"][0]
    assert split["resolution"] is None and split["resolutions"] == [[8, 8], [16, 16]]
    assert split["focal_min"] == 131.25 * 8 / 128 and split["focal_max"] == 131.25 * 16 / 128
    assert "mixed: 8x8, 16x16" in capsys.readouterr().out


@pytest.mark.parametrize("case", sorted(BAD_INPUT_CASES))
def test_inspect_bad_input_exit_2_naming_the_file(tmp_path: Path, case: str, capsys):
    root = make_srn_fixture(tmp_path, with_depth=True, with_mask=True)
    _, path, text = BAD_INPUT_CASES[case](root)
    assert main(["inspect", "--data", str(root)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and str(path) in err[0] and text in err[0]


def test_inspect_skip_bad_lists_skipped(tmp_path: Path, capsys):
    root = make_srn_fixture(tmp_path, splits={"train": 3, "test": 1})
    _, bad_pose, _ = BAD_INPUT_CASES["pose_not_rigid"](root)
    out_json = tmp_path / "s.json"
    assert main(["inspect", "--data", str(root), "--skip-bad", "--json", str(out_json)]) == 0
    out = capsys.readouterr().out
    assert "objects        2  (1 skipped)" in out and f"skipped: {bad_pose}: pose is not a rigid" in out
    train = json.loads(out_json.read_text())["splits"][0]
    assert train["objects"] == 2 and len(train["skipped"]) == 1 and str(bad_pose) in train["skipped"][0]


def test_inspect_as_a_process(tmp_path: Path):
    root = make_srn_fixture(tmp_path)
    BAD_INPUT_CASES["image_size_vs_intrinsics"](root)
    proc = subprocess.run([sys.executable, "-m", "depthnerf", "inspect", "--data", str(root)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.strip().startswith("error: ") and "000001.png: image is 20x20 but" in proc.stderr
