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


def test_interval_matches_scipys_paired_t_test(tmp_path: Path) -> None:
    """The 95% interval and standard error are scipy's paired t-test's (an independent implementation)."""
    pd = _load()
    base = [20.1, 22.4, 18.3, 25.0, 19.7, 21.2, 23.9]
    meth = [21.0, 22.5, 17.9, 26.2, 20.4, 21.0, 24.8]
    rows = {s.metric: s for s in pd.paired(_write(tmp_path / "b", "b", base, [0.1] * 7),
                                           _write(tmp_path / "m", "m", meth, [0.1] * 7))}
    ref = stats.ttest_rel(meth, base).confidence_interval(0.95)
    s = rows["psnr"]
    assert (s.ci95_low, s.ci95_high) == pytest.approx((ref.low, ref.high), abs=1e-12)
    assert s.std_err == pytest.approx(stats.sem([m - b for m, b in zip(meth, base, strict=True)]), abs=1e-12)


def _summary(folder: Path, **fields) -> None:
    data = {"method": folder.name, "category": "cars", "split": "test", "views_stride": 25, "resolution": 64,
            "protocol_choices": {"ssim": "uniform7", "scored": "png8", "skipped_objects": []}}
    for key, value in fields.items():
        data[key] = value
    (folder / "summary.json").write_text(json.dumps(data))


@pytest.mark.parametrize(("fields", "text"), [
    ({"views_stride": 26}, "--views-stride 26 but"),  # 250 targets: stride 25 and 26 both score 10 views
    ({"resolution": 128}, "--resolution 128 but"),
    ({"split": "val"}, "--split val but"),
    ({"protocol_choices": {"ssim": "uniform7", "scored": "float", "skipped_objects": []}}, "--scored float but"),
    ({"protocol_choices": {"ssim": "gaussian11", "scored": "png8", "skipped_objects": []}}, "--ssim gaussian11"),
    ({"protocol_choices": None, "metrics_path": "float renders (eval.py)"}, "--scored float but"),  # older summary
])
def test_evaluations_scored_on_other_views_or_another_way_are_not_paired(tmp_path: Path, fields, text) -> None:
    """Equal object ids and view counts are not enough: the summaries must say the same views were scored the
    same way (else a paired difference measures the protocol, not the method)."""
    pd = _load()
    base = _write(tmp_path / "base", "baseline", [20.0, 22.0], [0.1, 0.2])
    meth = _write(tmp_path / "meth", "depth", [21.0, 22.5], [0.1, 0.2])
    _summary(base)
    _summary(meth)
    assert [s.metric for s in pd.paired(base, meth)] == ["psnr", "chamfer_l1"]
    _summary(meth, **fields)
    for common in (False, True):
        with pytest.raises(SystemExit, match="not paired") as err:
            pd.paired(base, meth, common=common)
        assert text in str(err.value) and str(base / "summary.json") in str(err.value)


def test_another_input_view_is_other_views(tmp_path: Path) -> None:
    pd = _load()
    base = _write(tmp_path / "base", "baseline", [20.0, 22.0], [0.1, 0.2])
    meth = _write(tmp_path / "meth", "depth", [21.0, 22.5], [0.1, 0.2])
    for folder, view in ((base, "64"), (meth, "0")):
        with open(folder / "per_object.csv", newline="") as f:
            rows = list(csv.DictReader(f))
        with open(folder / "per_object.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=[*rows[0], "input_view"])
            w.writeheader()
            w.writerows({**r, "input_view": view} for r in rows)
    with pytest.raises(SystemExit, match="object obj0 was scored on other views"):
        pd.paired(base, meth)


def _write_columns(folder: Path, summary: dict, columns: dict[str, list[str]]) -> Path:
    """per_object.csv with the given metric columns (one value per object obj0, obj1, ...; "" = not scored)."""
    folder.mkdir(parents=True)
    (folder / "summary.json").write_text(json.dumps(summary))
    n = len(next(iter(columns.values())))
    with open(folder / "per_object.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["object_id", "views", *columns])
        w.writeheader()
        for k in range(n):
            w.writerow({"object_id": f"obj{k}", "views": "10", **{c: v[k] for c, v in columns.items()}})
    return folder


def test_common_objects_metric_directions_and_single_object_metrics(tmp_path: Path) -> None:
    """The method scored 3 of the baseline's 4 objects; its summary predates ``resolution`` (not compared).
    On the 3 shared objects: F-score d = (+0.1, +0.1, -0.1), higher is better: 2 wins; floater fraction
    d = (-0.05, 0, -0.1), lower is better: 2 wins, 3 no worse; SSIM was scored on one object only: no row."""
    pd = _load()
    base = _write_columns(tmp_path / "base", {"method": "b", "resolution": 64},
                          {"ssim": ["0.9", "", "", ""], "fscore": ["0.5", "0.6", "0.7", "0.8"],
                           "floater_fraction": ["0.1", "0.0", "0.2", "0.3"]})
    meth = _write_columns(tmp_path / "meth", {"method": "m"},
                          {"ssim": ["0.95", "", ""], "fscore": ["0.6", "0.7", "0.6"],
                           "floater_fraction": ["0.05", "0.0", "0.1"]})
    with pytest.raises(SystemExit, match="objects differ"):
        pd.paired(base, meth)
    rows = {s.metric: s for s in pd.paired(base, meth, common=True)}
    assert set(rows) == {"fscore", "floater_fraction"}
    f, fl = rows["fscore"], rows["floater_fraction"]
    assert (f.n, f.wins, f.no_worse) == (3, 2, 2) and (fl.n, fl.wins, fl.no_worse) == (3, 2, 3)
    assert f.baseline_mean == pytest.approx(0.6) and f.mean_diff == pytest.approx(0.1 / 3)
    assert fl.baseline_mean == pytest.approx(0.1) and fl.mean_diff == pytest.approx(-0.05)


def test_accuracy_and_completeness_are_paired_lower_is_better(tmp_path: Path) -> None:
    """The two halves of Chamfer-L1 (per_object.csv ``accuracy``, ``completeness``) get rows of their own, lower
    better: accuracy d = (+0.01, -0.02, +0.03): 1 win; completeness d = (0, -0.01, -0.01): 2 wins, 3 no worse."""
    pd = _load()
    base = _write_columns(tmp_path / "base", {"method": "b"},
                          {"accuracy": ["0.02", "0.05", "0.03"], "completeness": ["0.01", "0.02", "0.03"]})
    meth = _write_columns(tmp_path / "meth", {"method": "m"},
                          {"accuracy": ["0.03", "0.03", "0.06"], "completeness": ["0.01", "0.01", "0.02"]})
    rows = {s.metric: s for s in pd.paired(base, meth)}
    assert set(rows) == {"accuracy", "completeness"}
    a, c = rows["accuracy"], rows["completeness"]
    assert (a.wins, a.no_worse) == (1, 1) and a.mean_diff == pytest.approx(0.02 / 3)
    assert (c.wins, c.no_worse) == (2, 3) and c.mean_diff == pytest.approx(-0.02 / 3)


def _eval_with_views(folder: Path, data: Path, inputs: list[int] | None, per_view: dict[str, list[float]]) -> Path:
    """An eval folder of 12-view objects (``objects/<id>.json`` per-view PSNR in target order, per_object.csv with
    the per-object means and a Chamfer-L1), scored on every view but ``inputs`` (None: the default, view 0)."""
    (folder / "objects").mkdir(parents=True)
    summary = {"method": folder.name, "data_card": {"root": str(data)}, "category": "cars", "split": "test",
               "views_stride": 1, **({"input_views": inputs} if inputs else {})}
    (folder / "summary.json").write_text(json.dumps(summary))
    with open(folder / "per_object.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["object_id", "input_view", "input_views", "views", "psnr", "ssim",
                                          "chamfer_l1"])
        w.writeheader()
        for k, (oid, psnr) in enumerate(per_view.items()):
            views = [{"psnr": p, "ssim": 0.5, "lpips": None} for p in psnr]
            (folder / "objects" / f"{oid}.json").write_text(json.dumps({"metrics": {"views": views}}))
            w.writerow({"object_id": oid, "input_view": (inputs or [0])[0],
                        "input_views": " ".join(map(str, inputs or [0])), "views": len(psnr),
                        "psnr": sum(psnr) / len(psnr), "ssim": 0.5, "chamfer_l1": 0.1 * (k + 1)})
    return folder


def test_common_views_pair_one_input_view_against_two_on_the_views_both_scored(tmp_path: Path, capsys) -> None:
    """One input view (0: targets 1-11) against two (0 and 5: targets 1-4, 6-11): per view, PSNR = the view index
    for the baseline and index + 0.5 / + 1.5 for the method's two objects, so over the 10 shared views the
    baseline's mean is (66 - 5) / 10 and the differences 0.5 and 1.5; the Chamfer-L1 is paired as it is."""
    pd = _load()
    data = tmp_path / "data"
    for oid in ("a", "b"):
        (data / "cars_test" / oid / "rgb").mkdir(parents=True)
        for v in range(12):
            (data / "cars_test" / oid / "rgb" / f"{v:06d}.png").write_bytes(b"")
    one = [float(v) for v in range(1, 12)]
    two = [v for v in range(1, 12) if v != 5]
    base = _eval_with_views(tmp_path / "one", data, None, {"a": one, "b": one})
    meth = _eval_with_views(tmp_path / "two", data, [0, 5],
                            {"a": [v + 0.5 for v in two], "b": [v + 1.5 for v in two]})
    with pytest.raises(SystemExit, match=r"object a was scored on other views .* \(--common-views pairs"):
        pd.paired(base, meth)
    stats_by = {s.metric: s for s in pd.paired(base, meth, common_views=True)}
    psnr = stats_by["psnr"]
    assert psnr.n == 2 and math.isclose(psnr.baseline_mean, 6.1) and math.isclose(psnr.mean_diff, 1.0)
    assert math.isclose(psnr.std_err, 0.5) and psnr.wins == 2
    assert stats_by["chamfer_l1"].mean_diff == 0.0 and stats_by["ssim"].mean_diff == 0.0
    per_view = [line for line in capsys.readouterr().err.splitlines() if line.startswith("view ")]
    assert per_view == [f"view {v}: PSNR +1.00 +- 0.50 dB over 2 objects" for v in two]  # 0.5 and 1.5 per view


@pytest.mark.parametrize(("text", "says"), [
    ("id,psnr\nobj0,20\nobj1,21\n", "no object_id column"),
    ("object_id,psnr\nobj0,20\nobj0,21\n", "object obj0 is listed twice"),
    ("object_id,psnr\nobj0,20\nobj1,abc\n", "object obj1: psnr 'abc' is not a finite number"),
    ("object_id,psnr\nobj0,nan\nobj1,21\n", "object obj0: psnr 'nan' is not a finite number"),
])
def test_a_corrupt_per_object_csv_is_one_line_naming_it(tmp_path: Path, capsys, text: str, says: str) -> None:
    """A per_object.csv without the object_id column, with an object twice (the later row would replace the
    earlier) or with a metric cell that is not a finite number is refused in one line naming the file, for
    paired_difference.py and seed_paired_difference.py alike."""
    pd = _load()
    base = _write(tmp_path / "base", "baseline", [20.0, 22.0], [0.1, 0.2])
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "per_object.csv").write_text(text)
    for argv in (["--baseline", str(base), "--method", str(bad)], ["--baseline", str(bad), "--method", str(base)]):
        with pytest.raises(SystemExit) as err:
            pd.main(argv)
        assert str(err.value).startswith(f"error: {bad / 'per_object.csv'}: {says}") and "\n" not in str(err.value)
    spd = load_script("seed_paired_difference")
    with pytest.raises(SystemExit, match=f"error: {bad / 'per_object.csv'}: {says}"):
        spd.seed_paired([base], [bad])
    (bad / "per_object.csv").write_bytes(b"object_id,psnr\nobj0,20\n\xff\xfe,21\n")
    with pytest.raises(SystemExit, match=f"error: {bad / 'per_object.csv'}: unreadable"):
        pd.paired(base, bad)
