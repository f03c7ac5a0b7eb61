"""``depthnerf compare`` on hand-made eval summaries."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from depthnerf.cli import main
from depthnerf.eval.table import PAPER_LABEL


def _summary(path: Path, method: str, category: str, psnr: float, ssim: float, **extra) -> Path:
    data = {"psnr": psnr, "ssim": ssim, "objects": 3, "views": 150, "checkpoint_sha256": "ab" * 32,
            "preset": "cpu-small", "category": category, "depth_prior": extra.pop("depth_prior", "none"),
            "method": method, "protocol": "SRN: source view 64, 250 targets", **extra}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data))
    return path


def _rows(text: str) -> dict[str, list[str]]:
    """Markdown table -> {first cell: other cells}, plus the header under key 'Method'."""
    lines = [ln for ln in text.splitlines() if ln.startswith("| ")]
    return {cells[0]: cells[1:] for cells in ([c.strip() for c in ln.strip("|").split("|")] for ln in lines)}


@pytest.fixture
def runs(tmp_path: Path) -> dict[str, Path]:
    """A baseline run dir with two eval folders, a depth-aware eval out dir, and a bare summary file."""
    base = tmp_path / "runs" / "baseline"
    _summary(base / "eval" / "chairs_test" / "summary.json", "pixelNeRF (baseline)", "chairs", 21.234, 0.87654,
             lpips=0.1234)
    _summary(base / "eval" / "cars_test" / "summary.json", "pixelNeRF (baseline)", "cars", 20.5, 0.8)
    ours = _summary(tmp_path / "out" / "ours_chairs" / "summary.json", "depth-aware (bundled)", "chairs", 22.0,
                    0.9, depth_prior="bundled", chamfer_l1=0.012345, fscore=0.61, fscore_tau=0.01, lpips=None)
    return {"run": base, "eval_dir": ours.parent, "file": ours}


def test_table_has_table1_shape_and_missing_cells(runs, capsys):
    assert main(["compare", str(runs["run"]), str(runs["eval_dir"])]) == 0
    rows = _rows(capsys.readouterr().out)
    assert rows["Method"] == ["Chairs PSNR", "Chairs SSIM", "Chairs CD-L1", "Chairs F-score", "Chairs LPIPS",
                              "Cars PSNR", "Cars SSIM"]
    assert rows["pixelNeRF (baseline)"] == ["21.23", "0.877", "—", "—", "0.123", "20.50", "0.800"]
    assert rows["depth-aware (bundled)"] == ["22.00", "0.900", "0.0123", "0.610", "—", "—", "—"]
    assert len(rows) == 3


def test_reference_rows_are_labelled_and_out_file_matches(runs, tmp_path, capsys):
    out = tmp_path / "tables" / "table1.md"
    assert main(["compare", str(runs["file"]), "--reference", "paper", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert out.read_text() == text
    rows = _rows(text)
    assert rows["Method"] == ["Chairs PSNR", "Chairs SSIM", "Chairs CD-L1", "Chairs F-score", "Cars PSNR",
                              "Cars SSIM"]  # ours has lpips null: no LPIPS column
    paper = {k: v for k, v in rows.items() if PAPER_LABEL in k}
    assert paper[f"SRN — {PAPER_LABEL}"][:2] == ["22.89", "0.89"]
    assert paper[f"SRN — {PAPER_LABEL}"][-2:] == ["22.25", "0.88"]
    assert paper[f"pixelNeRF — {PAPER_LABEL}"][-2:] == ["23.17", "0.89"]
    assert paper[f"VisionNeRF — {PAPER_LABEL}"][:2] == ["24.48", "0.92"]
    assert paper[f"Ours (depth-aware pixelNeRF) — {PAPER_LABEL}"][:2] == ["24.26", "0.91"]
    assert paper[f"Ours (depth-aware pixelNeRF) — {PAPER_LABEL}"][-2:] == ["23.50", "0.90"]
    assert rows["depth-aware (bundled)"][-2:] == ["—", "—"]  # measured only on chairs
    assert "checkpoint abababababab" in text and "depth prior bundled" in text and "F-score tau 0.01" in text


def test_same_file_twice_is_one_row(runs, capsys):
    assert main(["compare", str(runs["file"]), str(runs["eval_dir"])]) == 0
    assert len(_rows(capsys.readouterr().out)) == 2


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda d: d.pop("checkpoint_sha256"), "summary is missing checkpoint_sha256"),
        (lambda d: d.update(psnr="22.1"), "'psnr' must be a finite number"),
        (lambda d: d.update(psnr=-1e9), "'psnr' is -1000000000.0, which no evaluation gives (it is >= 0)"),
        (lambda d: d.update(ssim=1.5), "'ssim' is 1.5, which no evaluation gives (it is within [-1, 1])"),
        (lambda d: d.update(fscore=-0.1), "'fscore' is -0.1, which no evaluation gives (it is within [0, 1])"),
        (lambda d: d.update(views=-1), "'views' must be a non-negative integer"),
        (lambda d: d.update(method=""), "'method' must be a non-empty string"),
    ],
)
def test_bad_summary_is_one_line_error(tmp_path, capsys, edit, match):
    path = _summary(tmp_path / "summary.json", "m", "cars", 20.0, 0.8)
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))
    assert main(["compare", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {path}: ") and match in err and err.count("\n") == 1


def test_bad_paths_and_conflicts(runs, tmp_path, capsys):
    (tmp_path / "broken.json").write_text("{not json")
    (tmp_path / "empty_dir").mkdir()
    twin = _summary(tmp_path / "twin" / "summary.json", "pixelNeRF (baseline)", "cars", 1.0, 0.1)
    for args, match in [
        ([str(tmp_path / "broken.json")], "not valid JSON"),
        ([str(tmp_path / "nowhere")], "no such file or directory"),
        ([str(tmp_path / "empty_dir")], "no summary.json here"),
        ([str(runs["run"]), str(twin)], "is also given by"),
        ([str(twin), "--out", str(tmp_path)], f"{tmp_path}: --out is a folder; name the Markdown file to write"),
        ([str(twin), "--out", str(twin / "t.md")], f"--out lies under {twin}, which is a file, not a folder"),
    ]:
        assert main(["compare", *args]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and match in err


def _choices(ssim: str = "uniform7", scored: str = "png8", skipped: tuple[str, ...] = ()) -> dict:
    return {"ssim": ssim, "scored": scored, "objects": "pixelnerf" if skipped else "all",
            "skipped_objects": list(skipped)}


def _per_object(*ids: str) -> list[dict]:
    return [{"object_id": i, "views": 10, "psnr": 20.0, "ssim": 0.8, "lpips": None} for i in ids]


@pytest.mark.parametrize(("a", "b", "match"), [
    ({"protocol_choices": _choices("uniform7")}, {"protocol_choices": _choices("gaussian11")},
     "with --ssim gaussian11 but"),
    ({"protocol_choices": _choices(scored="png8")}, {"metrics_path": "float renders (eval.py)"},  # older summary
     "with --scored float but"),
    ({"protocol_choices": _choices(skipped=("w",)), "per_object": _per_object("x")},
     {"protocol_choices": _choices(), "per_object": _per_object("x", "w")},
     "left out object w (--objects pixelnerf) but"),
])
def test_summaries_with_other_protocol_choices_are_refused(tmp_path, capsys, a, b, match):
    first = _summary(tmp_path / "a" / "summary.json", "ours", "cars", 20.0, 0.8, **a)
    second = _summary(tmp_path / "b" / "summary.json", "theirs", "cars", 21.0, 0.81, **b)
    assert main(["compare", str(first), str(second)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and match in err and "--mixed-protocols" in err
    assert str(first) in err and str(second) in err
    assert main(["compare", str(first), str(second), "--mixed-protocols"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("**WARNING: mixed protocol choices") and match in out
    assert set(_rows(out)) == {"Method", "ours", "theirs"}


def test_agreeing_protocol_choices_are_stated_under_the_table(tmp_path, capsys):
    cars = _summary(tmp_path / "cars" / "summary.json", "ours", "cars", 20.0, 0.8,
                    protocol_choices=_choices(skipped=("w",)), per_object=_per_object("x"))
    older = _summary(tmp_path / "old" / "summary.json", "older", "cars", 19.0, 0.7,  # before choices were recorded
                     metrics_path="quantized 8-bit renders (calc_metrics.py)", per_object=_per_object("x"))
    chairs = _summary(tmp_path / "chairs" / "summary.json", "ours", "chairs", 22.0, 0.9,
                      protocol_choices=_choices(), per_object=_per_object("w"))  # another category's "w"
    assert main(["compare", str(cars), str(older), str(chairs)]) == 0
    out = capsys.readouterr().out
    assert out.endswith("Protocol choices of every measured row: SSIM uniform7, png8 renders scored, left out "
                        "(pixelNeRF cannot load them): w.\n")


def test_rows_over_different_samples_are_printed_with_a_warning(tmp_path, capsys):
    """Same protocol choices, but one chairs row scored 3 objects x 150 views and the other 2 x 20: the table is
    printed, and stderr says which category's rows average different samples; equal samples say nothing."""
    a = _summary(tmp_path / "a" / "summary.json", "baseline", "chairs", 21.0, 0.87)
    b = _summary(tmp_path / "b" / "summary.json", "depth-aware", "chairs", 22.0, 0.9, objects=2, views=20)
    c = _summary(tmp_path / "c" / "summary.json", "baseline", "cars", 20.0, 0.8)
    assert main(["compare", str(a), str(b), str(c)]) == 0
    out, err = capsys.readouterr()
    assert "depth-aware" in out and err == ("warning: the chairs rows were scored on different samples (2 objects x "
                                            "20 views; 3 objects x 150 views): their means are not over the same "
                                            "views\n")
    assert main(["compare", str(a), str(c)]) == 0
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize(("a", "b", "text"), [
    ({"views_stride": 25}, {"views_stride": 26}, "with different --views-stride (25; 26)"),  # 10 views each
    ({"resolution": 64}, {"resolution": 128}, "with different --resolution (128; 64)"),
    ({"split": "test"}, {"split": "val"}, "with different splits (test; val)"),
    ({"input_views": [64]}, {"input_views": [64, 104]}, "with different --input-views ([64, 104]; [64])"),
    ({"per_object": _per_object("x", "y", "z")}, {"per_object": _per_object("x", "y", "w")},
     "on different objects (as many in each)"),
])
def test_rows_over_other_views_with_equal_counts_are_printed_with_a_warning(tmp_path, capsys, a, b, text):
    """Equal numbers of objects and views do not make the same sample: another stride, resolution, split or set
    of objects is said on stderr too."""
    first = _summary(tmp_path / "a" / "summary.json", "baseline", "cars", 20.0, 0.8, **a)
    second = _summary(tmp_path / "b" / "summary.json", "depth-aware", "cars", 21.0, 0.81, **b)
    assert main(["compare", str(first), str(second)]) == 0
    out, err = capsys.readouterr()
    assert "depth-aware" in out and err == (f"warning: the cars rows were scored {text}: their means are not over "
                                            "the same views\n")
    same = _summary(tmp_path / "c" / "summary.json", "depth-aware", "cars", 21.0, 0.81, **a)
    assert main(["compare", str(first), str(same)]) == 0
    assert capsys.readouterr().err == ""
