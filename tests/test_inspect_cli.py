"""``depthnerf inspect``: summary, --json content, bad input through the CLI (exit 2, file named), --skip-bad,
third-party layouts (formats, warnings, --strict); ``depthnerf eval`` checks every file up front."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from fixtures_srn import BAD_INPUT_CASES, make_srn_fixture
from fixtures_wild import BAD_OPTIONAL_CASES, to_third_party_style

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


@pytest.mark.parametrize("where, said", [("folder", "--json is a folder; name the file to write"),
                                         ("under a file", "--json lies under")])
def test_inspect_refuses_a_json_path_it_cannot_write_before_indexing(tmp_path: Path, where: str, said: str, capsys):
    """The summary is written last: a ``--json`` that cannot take it is one line before any split is read, and
    nothing is left beside it."""
    root = make_srn_fixture(tmp_path / "data", splits={"train": 1}, views=2, size=8)
    (tmp_path / "a_file").write_text("")
    target = {"folder": tmp_path / "out", "under a file": tmp_path / "a_file" / "s.json"}[where]
    (tmp_path / "out").mkdir()
    before = sorted(tmp_path.iterdir())
    assert main(["inspect", "--data", str(root), "--json", str(target)]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.startswith(f"error: {target}: {said}") and err.count("\n") == 1, (out, err)
    assert sorted(tmp_path.iterdir()) == before and not any((tmp_path / "out").iterdir())


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


@pytest.mark.parametrize("card, said", [
    ("[1, 2]", ": unreadable dataset card"),
    ('{"camera": {"pixel_center": "half"}}', ": camera.pixel_center must be a number in [0, 1]"),
    ('{"framing": "blender"}', " framing: unknown framing 'blender'"),
    ('{"objects": {"front": "+x", "up": "+x"}}', ": objects.front +x and objects.up +x are parallel"),
])
def test_inspect_reads_the_dataset_card_as_train_and_eval_do(tmp_path: Path, card: str, said: str, capsys):
    """A card training or evaluation would stop on is an error of inspect too, not a clean bill of health."""
    root = make_srn_fixture(tmp_path, splits={"train": 1}, views=2, size=8)
    (root / "cars_card.json").write_text(card)
    assert main(["inspect", "--data", str(root)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"error: {root / 'cars_card.json'}{said}" + err[0].split(said, 1)[1]]


def test_inspect_compares_the_cards_camera_with_the_files(tmp_path: Path, capsys):
    """A card's camera fields were written and never read: a card made for other files (another resolution, say)
    passed silently, its pixel centre and framing then applied to files it does not describe."""
    root = make_srn_fixture(tmp_path / "data", splits={"train": 1}, views=2, size=16)
    card = root / "cars_card.json"
    camera = {"height": 16, "width": 16, "focal": 131.25 * 16 / 128, "radius": 1.3, "pixel_center": 0.5}
    card.write_text(json.dumps({"camera": camera}))
    assert main(["inspect", "--data", str(root), "--json", str(tmp_path / "s.json")]) == 0
    assert "warning" not in capsys.readouterr().err  # agreeing to the files' 6 decimals
    card.write_text(json.dumps({"camera": {**camera, "height": 32, "width": 32, "focal": 32.8125, "radius": 1.5}}))
    assert main(["inspect", "--data", str(root), "--json", str(tmp_path / "s.json")]) == 0
    said = (f"{card}: the card's camera says images 32x32, the files 16x16; focal 32.81 px, the files 16.41 px; "
            f"cameras 1.5 from the origin, the files 1.3 ({root / 'cars_train'}): the card describes other files, and "
            "its pixel_center and framing may not hold for these")
    assert capsys.readouterr().err.strip() == f"warning: {said}"
    assert json.loads((tmp_path / "s.json").read_text())["splits"][0]["warnings"] == [said]
    assert main(["inspect", "--data", str(root), "--strict"]) == 2
    assert capsys.readouterr().err.strip() == f"error: {said}"


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


def test_inspect_reports_what_a_third_party_layout_holds(tmp_path: Path, capsys):
    root = make_srn_fixture(tmp_path, splits={"train": 4, "test": 1}, with_depth=True, with_mask=True, with_mesh=True)
    to_third_party_style(root)
    out_json = tmp_path / "s.json"
    assert main(["inspect", "--data", str(root), "--json", str(out_json)]) == 0
    captured = capsys.readouterr()
    train, test = json.loads(out_json.read_text())["splits"]
    assert train["objects"] == 4 and train["objects_with_depth"] == train["objects_with_mask"] == 4
    assert train["rgb_formats"] == {"PNG 8-bit RGB": 12}
    assert train["depth_formats"] == {".npy": 3, ".npz": 6, "16-bit PNG": 3}
    assert train["mask_formats"] == {"PNG 1-bit grey": 3, "PNG 1-bit palette": 3, "PNG 16-bit grey": 3,
                                     "PNG 8-bit RGBA": 3}
    assert train["ignored"] == {"meta.json": 1, "normal/": 1, "render_log.txt": 1}
    assert train["warnings"] == [] and train["unusable"] == {} and test["ignored"] == {}
    assert test["depth_formats"] == {".npz": 3} and test["mask_formats"] == {"PNG 8-bit grey": 3}
    assert "depth          all  [.npy (3 views), .npz (6 views), 16-bit PNG (3 views)]" in captured.out
    assert "ignored        meta.json (1 objects), normal/ (1 objects)" in captured.out
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("note: ") and "render_log.txt (1)" in err[0]


@pytest.mark.parametrize("case", ["depth_png_without_scale", "depth_nan_filled", "mask_truncated", "mesh_not_ply",
                                  "mesh_face_out_of_range", "mesh_nan_vertex"])
def test_inspect_bad_optional_part_warns_and_strict_fails(tmp_path: Path, case: str, capsys):
    root = make_srn_fixture(tmp_path, with_depth=True, with_mask=True, with_mesh=True)
    part, mutate = BAD_OPTIONAL_CASES[case]
    path, text = mutate(root)
    out_json = tmp_path / "s.json"
    assert main(["inspect", "--data", str(root), "--json", str(out_json)]) == 0
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"warning: {path}: ") and text in err[0]
    train = json.loads(out_json.read_text())["splits"][0]
    assert train["unusable"] == {part: 1} and len(train["warnings"]) == 1 and str(path) in train["warnings"][0]
    assert train[f"objects_with_{part}"] == 1 and "warnings       1" in captured.out
    assert "(unusable in 1 more objects, see warnings)" in captured.out
    assert main(["inspect", "--data", str(root), "--strict"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {path}: ") and text in err[0]


def test_eval_reports_a_corrupt_unscored_view_up_front(tmp_path: Path, capsys):
    root = make_srn_fixture(tmp_path / "data", splits={"test": 1}, views=3)
    bad = sorted((root / "cars_test").iterdir())[0] / "rgb" / "000002.png"
    bad.write_bytes(bad.read_bytes()[:60])  # input view 0, scored view 1 (--views-stride 2): view 2 is not scored
    out = tmp_path / "eval"
    assert main(["eval", "--checkpoint", "cpu-cars-baseline", "--data", str(root), "--out", str(out),
                 "--views-stride", "2", "--no-mesh", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {bad}: unreadable image")
    assert not (out / "summary.json").exists()


@pytest.mark.parametrize("command", [
    ["train", "--out", "{tmp}/run", "--max-steps", "1"],
    ["eval", "--checkpoint", "cpu-cars-baseline", "--out", "{tmp}/eval", "--split", "train", "--no-progress"],
    ["depth", "--estimator", "bundled", "--splits", "train", "--no-progress"],
])
def test_strict_flag_of_train_eval_depth(tmp_path: Path, command: list[str], capsys):
    root = make_srn_fixture(tmp_path / "data", with_depth=True, with_mask=True)
    path, text = BAD_OPTIONAL_CASES["mask_size_vs_intrinsics"][1](root)
    args = [a.format(tmp=tmp_path) for a in command] + ["--data", str(root), "--strict"]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {path}: ") and text in err[0]
    assert not (tmp_path / "run").exists() and not (tmp_path / "eval").exists()
