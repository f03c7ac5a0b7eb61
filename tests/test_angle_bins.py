"""scripts/angle_bins.py against angles and paired statistics computed by hand."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from fixtures_scripts import load_script

from depthnerf.data.cameras import look_at
from tests.fixtures_srn import make_srn_fixture

AZIMUTHS = (0.0, 30.0, 100.0, 170.0)
"""Azimuths of the four views of :func:`_horizontal_cameras`."""


def _load():
    return load_script("angle_bins")


def _eval(folder: Path, root: Path, psnr: dict[tuple[str, int], float]) -> Path:
    folder.mkdir(parents=True)
    (folder / "summary.json").write_text(json.dumps({"data_card": {"root": str(root)}, "category": "cars",
                                                     "split": "test", "views_stride": 1,
                                                     "renders_csv": "renders.csv"}))
    ids = sorted({oid for oid, _ in psnr})
    with open(folder / "per_object.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["object_id", "input_view"])
        w.writeheader()
        w.writerows({"object_id": oid, "input_view": 0} for oid in ids)
    with open(folder / "renders.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["object_id", "view", "psnr", "ssim"])
        w.writeheader()
        w.writerows({"object_id": oid, "view": v, "psnr": p, "ssim": p / 100} for (oid, v), p in psnr.items())
    return folder


def _horizontal_cameras(root: Path) -> None:
    """Every test object's four views on a horizontal circle at azimuths 0, 30, 100 and 170 degrees, so the angle
    of view k to view 0 is its azimuth."""
    for obj in sorted((root / "cars_test").iterdir()):
        for k, az in enumerate(AZIMUTHS):
            a = math.radians(az)
            pose = look_at(torch.tensor([1.3 * math.cos(a), 1.3 * math.sin(a), 0.0])).numpy()
            np.savetxt(obj / "pose" / f"{k:06d}.txt", pose.reshape(1, 16))


def test_bins_follow_the_camera_angle_and_pair_per_object(tmp_path):
    root = make_srn_fixture(tmp_path / "data", "cars", splits={"test": 3}, views=4, size=8)
    _horizontal_cameras(root)
    ids = sorted(p.name for p in (root / "cars_test").iterdir())
    base = {(oid, v): 20.0 + v for oid in ids for v in (1, 2, 3)}
    gain = {ids[0]: 1.0, ids[1]: 2.0, ids[2]: 0.0}
    method = {(oid, v): p + (gain[oid] if v == 3 else 0.5) for (oid, v), p in base.items()}
    mod = _load()
    b, m = _eval(tmp_path / "base", root, base), _eval(tmp_path / "method", root, method)
    angles = mod.view_angles(b)
    assert [round(angles[(ids[0], v)], 4) for v in (1, 2, 3)] == [30.0, 100.0, 170.0]
    rows = {(r["bin"], r["metric"]): r for r in mod.compare(mod.binned(b, [0, 45, 90, 135, 180], angles),
                                                             mod.binned(m, [0, 45, 90, 135, 180], angles),
                                                             [0, 45, 90, 135, 180])}
    assert ("45-90", "psnr") not in rows  # no view there
    assert rows[("0-45", "psnr")]["diff"] == pytest.approx(0.5) and rows[("0-45", "psnr")]["wins"] == 3
    far = rows[("135-180", "psnr")]
    d = np.array([1.0, 2.0, 0.0])
    half = 4.302652729911275 * d.std(ddof=1) / math.sqrt(3)  # t_{0.975, 2}
    assert far["diff"] == pytest.approx(1.0) and far["ci95"] == pytest.approx([1.0 - half, 1.0 + half])
    assert far["wins"] == 2 and far["objects"] == 3 and far["views"] == 3
    assert mod.main(["--baseline", str(b), "--method", str(m), "--json", str(tmp_path / "o.json")]) == 0
    assert json.loads((tmp_path / "o.json").read_text())[str(m)][0]["bin"] == "0-45"


def _folders(tmp_path: Path) -> tuple[Path, Path]:
    root = make_srn_fixture(tmp_path / "data", "cars", splits={"test": 2}, views=4, size=8)
    ids = sorted(p.name for p in (root / "cars_test").iterdir())
    psnr = {(oid, v): 20.0 + v for oid in ids for v in (1, 2, 3)}
    return _eval(tmp_path / "base", root, psnr), _eval(tmp_path / "method", root, psnr)


def _main_error(mod, capsys, *argv: str) -> str:
    assert mod.main([str(a) for a in argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1, err
    return err


def test_missing_folder_or_file_is_one_error_line(tmp_path, capsys):
    mod = _load()
    b, m = _folders(tmp_path)
    err = _main_error(mod, capsys, "--baseline", tmp_path / "missing", "--method", m)
    assert f"{tmp_path / 'missing'}: no such eval folder" in err
    (m / "summary.json").unlink()
    assert f"{m / 'summary.json'}: missing" in _main_error(mod, capsys, "--baseline", b, "--method", m)
    (b / "per_object.csv").unlink()
    assert f"{b / 'per_object.csv'}: missing" in _main_error(mod, capsys, "--baseline", b, "--method", b)
    assert "--bins needs" in _main_error(mod, capsys, "--baseline", b, "--method", b, "--bins", "0", "200")


def test_renders_csv_of_another_evaluation_is_refused(tmp_path, capsys):
    """A renders.csv the summary does not name (evaluated without --save-renders), or whose views are not the
    summary's views_stride targets, is an earlier evaluation's: refused in one line."""
    mod = _load()
    b, m = _folders(tmp_path)
    assert mod.main(["--baseline", str(b), "--method", str(m)]) == 0
    capsys.readouterr()
    summary = json.loads((m / "summary.json").read_text())
    (m / "summary.json").write_text(json.dumps({**summary, "renders_csv": None}))
    err = _main_error(mod, capsys, "--baseline", b, "--method", m)
    assert f"{m / 'renders.csv'}: not written by the evaluation of {m / 'summary.json'}" in err
    (m / "summary.json").write_text(json.dumps({**summary, "views_stride": 2}))  # targets (1, 3), renders 1, 2, 3
    err = _main_error(mod, capsys, "--baseline", b, "--method", m)
    assert "not the 2 targets of views_stride 2" in err and "renders.csv of another evaluation" in err
    (m / "summary.json").write_text(json.dumps(summary))
    with open(m / "per_object.csv", "a", newline="") as f:
        f.write("0123456789abcdef0123456789abcdef,0\n")
    assert "(other objects)" in _main_error(mod, capsys, "--baseline", b, "--method", m)


def test_views_beyond_the_last_edge_are_in_no_bin(tmp_path):
    """With edges 0, 45, 90 the views at 100 and 170 degrees belong to no bin (not to 45-90); 90 itself, the last
    edge, to the last bin, and a view below the first edge to none."""
    mod = _load()
    root = make_srn_fixture(tmp_path / "data", "cars", splits={"test": 2}, views=4, size=8)
    _horizontal_cameras(root)
    ids = sorted(p.name for p in (root / "cars_test").iterdir())
    b = _eval(tmp_path / "base", root, {(oid, v): 20.0 + v for oid in ids for v in (1, 2, 3)})
    bins = mod.binned(b, [0, 45, 90], mod.view_angles(b))
    assert set(bins) == {0} and all(o["views"] == 1 and o["psnr"] == 21.0 for o in bins[0].values())
    assert [mod.bin_index(a, [0, 45, 90]) for a in (0, 44.9, 45, 90, 100, 170)] == [0, 0, 1, 1, None, None]
    assert mod.bin_index(10, [20, 90]) is None


@pytest.mark.parametrize(("edit", "text"), [
    ({"views_stride": 2}, "--views-stride"),
    ({"resolution": 128}, "--resolution 128 but"),
    ({"protocol_choices": {"ssim": "gaussian11", "scored": "png8", "skipped_objects": []}}, "--ssim gaussian11"),
])
def test_a_method_scored_on_other_views_or_another_way_is_refused(tmp_path, capsys, edit, text):
    mod = _load()
    b, m = _folders(tmp_path)
    if "views_stride" in edit:  # a valid evaluation of its own: stride 2 scores views 1 and 3
        with open(m / "renders.csv", newline="") as f:
            rows = [r for r in csv.DictReader(f) if r["view"] != "2"]
        with open(m / "renders.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
    recorded = {"resolution": 64, "protocol_choices": {"ssim": "uniform7", "scored": "png8", "skipped_objects": []}}
    for folder, extra in ((b, {}), (m, edit)):
        summary = json.loads((folder / "summary.json").read_text())
        (folder / "summary.json").write_text(json.dumps({**summary, **recorded, **extra}))
    err = _main_error(mod, capsys, "--baseline", b, "--method", m)
    assert text in err and "not paired" in err


def test_an_evaluation_with_chosen_input_views_is_binned_on_its_targets(tmp_path, capsys):
    """``depthnerf eval --input-views 0 2`` scores views 1 and 3 of 4-view objects (summary.json ``input_views``
    [0, 2]): those are its targets, not another evaluation's; angles are measured from the primary input view 0."""
    mod = _load()
    root = make_srn_fixture(tmp_path / "data", "cars", splits={"test": 2}, views=4, size=8)
    _horizontal_cameras(root)
    ids = sorted(p.name for p in (root / "cars_test").iterdir())
    folders = []
    for name, gain in (("base", 0.0), ("method", 1.0)):
        folder = _eval(tmp_path / name, root, {(oid, v): 20.0 + v + gain for oid in ids for v in (1, 3)})
        summary = json.loads((folder / "summary.json").read_text())
        (folder / "summary.json").write_text(json.dumps({**summary, "input_views": [0, 2]}))
        folders.append(folder)
    assert mod.main(["--baseline", str(folders[0]), "--method", str(folders[1])]) == 0, capsys.readouterr().err
    angles = mod.view_angles(folders[0])
    assert sorted(round(a, 4) for (oid, _), a in angles.items() if oid == ids[0]) == [30.0, 170.0]
    rows = {r["bin"]: r for r in mod.compare(mod.binned(folders[0], [0, 90, 180], angles),
                                             mod.binned(folders[1], [0, 90, 180], angles), [0, 90, 180])
            if r["metric"] == "psnr"}
    assert rows["0-90"]["diff"] == pytest.approx(1.0) and rows["90-180"]["wins"] == 2


def test_a_method_conditioned_on_other_input_views_is_refused(tmp_path, capsys):
    """One input view against two (summary.json ``input_views`` [0] against [0, 2]): the bins would hold other
    views of each, so not paired (paired_difference.py --common-views pairs the views both scored)."""
    mod = _load()
    root = make_srn_fixture(tmp_path / "data", "cars", splits={"test": 2}, views=4, size=8)
    ids = sorted(p.name for p in (root / "cars_test").iterdir())
    folders = []
    for name, views, inputs in (("base", (1, 2, 3), [0]), ("method", (1, 3), [0, 2])):
        folder = _eval(tmp_path / name, root, {(oid, v): 20.0 + v for oid in ids for v in views})
        summary = json.loads((folder / "summary.json").read_text())
        (folder / "summary.json").write_text(json.dumps({**summary, "input_views": inputs}))
        folders.append(folder)
    err = _main_error(mod, capsys, "--baseline", folders[0], "--method", folders[1])
    assert "--input-views 0 2 but" in err and "not paired" in err


@pytest.mark.parametrize("name, edit, text", [
    ("renders.csv", lambda t: t.replace("psnr,", "score,", 1), "no psnr column"),
    ("renders.csv", lambda t: t.replace("21.0", "n/a", 1), "psnr 'n/a' is not a finite number"),
    ("renders.csv", lambda t: t.replace("21.0", "nan", 1), "psnr 'nan' is not a finite number"),
    ("per_object.csv", lambda t: t.replace("input_view", "first_view"), "no input_view column"),
    ("per_object.csv", lambda t: t.replace(",0", ",0.5", 1), "input_view '0.5' is not a finite number"),
])
def test_a_corrupt_csv_is_one_line_naming_it(tmp_path, capsys, name, edit, text):
    mod = _load()
    b, m = _folders(tmp_path)
    (m / name).write_text(edit((m / name).read_text()))
    err = _main_error(mod, capsys, "--baseline", b, "--method", m)
    assert f"{m / name}: " in err and text in err, err
    (m / name).write_bytes(b"\xff\xfe\x00bad")
    assert f"{m / name}: unreadable" in _main_error(mod, capsys, "--baseline", b, "--method", m)
