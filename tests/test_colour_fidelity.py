"""scripts/colour_fidelity.py's per-view measure against CIELAB values worked out by hand."""

from __future__ import annotations

import numpy as np
import pytest
from fixtures_scripts import load_script


def _load():
    return load_script("colour_fidelity")  # it imports angle_bins from beside it


def test_grey_render_of_a_coloured_object_loses_all_its_chroma():
    colour = _load()
    gt = np.full((8, 8, 3), 255, np.uint8)
    gt[2:6, 2:6] = (200, 40, 40)  # a red square on white
    grey = np.full((8, 8, 3), 255, np.uint8)
    grey[2:6, 2:6] = (90, 90, 90)
    same = colour.view_colour(gt, gt, white=0.95)
    assert same[0] == pytest.approx(same[1]) and same[2] == pytest.approx(0.0, abs=1e-9)
    chroma, gt_chroma, delta_ab = colour.view_colour(grey, gt, white=0.95)
    assert chroma == pytest.approx(0.0, abs=1e-2)  # neutral grey: a = b = 0 (to the matrices' rounding, ~2e-3)
    assert delta_ab == pytest.approx(gt_chroma, rel=1e-3)  # the distance from (0, 0) is the ground truth's chroma
    assert gt_chroma > 50  # a saturated red (CIELAB chroma of sRGB (200, 40, 40) is about 70)
    # only the ground truth's object pixels count: a white render there is as grey as the grey one
    white_render = np.full((8, 8, 3), 255, np.uint8)
    assert colour.view_colour(white_render, gt, white=0.95)[0] == pytest.approx(0.0, abs=1e-2)
    assert colour.view_colour(grey, np.full((8, 8, 3), 255, np.uint8), white=0.95) is None  # no object


def test_paired_colour_pairs_the_objects_both_scored_per_bin():
    """Differences over the common objects only, a hand-worked t-interval, the objects with a lower error."""
    colour = _load()
    row = lambda chroma, delta: np.array([chroma, 9.0, delta])  # noqa: E731  (chroma, gt chroma, delta ab)
    base = {"0-90": {"a": row(2.0, 4.0), "b": row(2.0, 5.0), "c": row(1.0, 6.0), "only-base": row(0.0, 0.0)},
            "90-180": {"a": row(1.0, 7.0)}}
    method = {"0-90": {"a": row(3.0, 3.0), "b": row(2.5, 5.5), "c": row(1.0, 4.0)}, "90-180": {"b": row(1.0, 1.0)}}
    got = colour.paired_colour(base, method)
    assert list(got) == ["0-90"]  # no object scored by both in 90-180
    r = got["0-90"]
    diffs = np.array([-1.0, 0.5, -2.0])
    se = diffs.std(ddof=1) / np.sqrt(3)
    assert r["objects"] == 3 and r["lower"] == 2
    assert r["delta_ab_diff"] == pytest.approx(diffs.mean()) and r["delta_ab_hw"] == pytest.approx(4.302653 * se)
    assert r["delta_ab_baseline"] == pytest.approx(5.0) and r["delta_ab_method"] == pytest.approx(12.5 / 3)
    assert r["chroma_diff"] == pytest.approx(0.5)


def test_float_images_as_read_rgb_gives_them_mask_the_same_object_pixels(tmp_path):
    """``read_rgb`` returns floats in [0, 1]: the white background must stay out of the mask as with 8-bit arrays
    (it once counted every pixel of a float image, diluting chroma with the background)."""
    from PIL import Image

    from depthnerf.data.srn_format import read_rgb

    colour = _load()
    gt = np.full((8, 8, 3), 255, np.uint8)
    gt[2:6, 2:6] = (40, 160, 60)
    render = np.full((8, 8, 3), 255, np.uint8)
    render[2:6, 2:6] = (60, 60, 160)
    Image.fromarray(gt).save(tmp_path / "gt.png")
    Image.fromarray(render).save(tmp_path / "render.png")
    from_files = colour.view_colour(read_rgb(tmp_path / "render.png"), read_rgb(tmp_path / "gt.png"), white=0.95)
    assert from_files == pytest.approx(colour.view_colour(render, gt, white=0.95), rel=1e-6)
    assert from_files[1] > 40  # the green square's own chroma, not a mean over 64 mostly white pixels


def test_colour_probe_recovers_an_exact_linear_map_and_scores_a_constant_guess_at_zero():
    """scripts/colour_probe.py's ridge probe: colours that are a linear function of the features are predicted on
    held-out rows with R^2 = 1 (a vanishing penalty); features that carry nothing leave R^2 at or below 0."""
    probe = load_script("colour_probe")
    gen = np.random.default_rng(0)
    x = gen.normal(size=(400, 6))
    y = x @ gen.normal(size=(6, 3)) + np.array([0.2, 0.5, 0.7])
    exact = probe.ridge_probe(x[:300], y[:300], x[300:], y[300:], alpha=1e-9)
    assert np.allclose(exact["r2"], 1.0, atol=1e-9) and exact["rmse"] < 1e-8
    noise = probe.ridge_probe(gen.normal(size=(300, 6)), y[:300], gen.normal(size=(100, 6)), y[300:], alpha=1.0)
    assert max(noise["r2"]) < 0.05


def _colour_eval(tmp_path, azimuths):
    """An eval folder of 2 fixture objects whose views sit at ``azimuths`` (degrees) around the input view 0, each
    target's render a uniform colour that says which view it is (its red channel: 20 * view)."""
    import csv
    import json
    import math

    import torch
    from PIL import Image

    from depthnerf.data.cameras import look_at
    from tests.fixtures_srn import make_srn_fixture

    root = make_srn_fixture(tmp_path / "data", "cars", splits={"test": 2}, views=len(azimuths), size=8)
    folder = tmp_path / "eval"
    (folder / "renders").mkdir(parents=True)
    ids = sorted(p.name for p in (root / "cars_test").iterdir())
    rows = []
    for oid in ids:
        for k, az in enumerate(azimuths):
            a = math.radians(az)
            pose = look_at(torch.tensor([1.3 * math.cos(a), 1.3 * math.sin(a), 0.0])).numpy()
            np.savetxt(root / "cars_test" / oid / "pose" / f"{k:06d}.txt", pose.reshape(1, 16))
            if k == 0:
                continue
            Image.fromarray(np.full((8, 8, 3), (20 * k, 120, 60), np.uint8)).save(folder / "renders" / f"{oid}_{k}.png")
            rows.append({"object_id": oid, "view": k, "psnr": 20.0, "ssim": 0.5,
                         "render_path": f"renders/{oid}_{k}.png",
                         "gt_path": str(root / "cars_test" / oid / "rgb" / f"{k:06d}.png")})
    (folder / "summary.json").write_text(json.dumps({"data_card": {"root": str(root)}, "category": "cars",
                                                     "split": "test", "views_stride": 1,
                                                     "renders_csv": "renders.csv"}))
    for name, fields, data in (("per_object.csv", ["object_id", "input_view"],
                                [{"object_id": oid, "input_view": 0} for oid in ids]),
                               ("renders.csv", list(rows[0]), rows)):
        with open(folder / name, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=fields)
            w.writeheader()
            w.writerows(data)
    return folder


def test_views_are_binned_as_angle_bins_bins_them(tmp_path):
    """A view is in the bin with ``lo <= angle < hi`` (the last one its upper edge too) and in no bin outside the
    edges, as scripts/angle_bins.py bins PSNR: with edges 45, 90, 180 the view at 30 degrees is left out (not put
    in 45-90), and with edges 0, 90 the views at 100 and 170 degrees are left out."""
    colour = _load()
    folder = _colour_eval(tmp_path, [0.0, 30.0, 100.0, 170.0])
    render = lambda k: np.full((8, 8, 3), (20 * k, 120, 60), np.uint8)  # noqa: E731
    got = colour.object_colour(folder, [45, 90, 180], white=0.95)
    assert set(got) == {"90-180"}
    for oid, value in got["90-180"].items():
        gt = colour.read_rgb(folder.parent / "data" / "cars_test" / oid / "rgb" / "000002.png")
        gt3 = colour.read_rgb(folder.parent / "data" / "cars_test" / oid / "rgb" / "000003.png")
        want = np.mean([colour.view_colour(render(2), gt, 0.95), colour.view_colour(render(3), gt3, 0.95)], axis=0)
        assert value == pytest.approx(want, rel=1e-9)
    near = colour.object_colour(folder, [0, 90], white=0.95)
    assert set(near) == {"0-90"} and len(near["0-90"]) == 2
    assert colour.object_colour(folder, [90, 0, 45], white=0.95).keys() == {"0-45"}  # edges in any order


def test_a_missing_folder_or_an_eval_scored_another_way_is_one_error_line(tmp_path, monkeypatch, capsys):
    """As scripts/angle_bins.py: a missing eval folder, and a folder paired with a ``--baseline`` scored at another
    ``--resolution`` (paired_difference.pairing_refusal), are one ``error:`` line and exit status 2."""
    import json
    import sys

    colour = _load()
    base, method = (_colour_eval(tmp_path / name, [0.0, 30.0, 100.0]) for name in ("b", "m"))

    def run(*argv):
        monkeypatch.setattr(sys, "argv", ["colour_fidelity.py", *map(str, argv)])
        assert colour.main() == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and err.count("\n") == 1, err
        return err

    assert f"{tmp_path / 'nowhere'}: no such eval folder" in run(tmp_path / "nowhere")
    assert f"{tmp_path / 'nowhere'}: no such eval folder" in run("--baseline", tmp_path / "nowhere", method)
    assert colour.main(["--baseline", str(base), str(method), "--bins", "0", "90", "180"]) == 0
    assert "| eval | 0-90 | 2 |" in capsys.readouterr().out
    for folder, res in ((base, 64), (method, 128)):
        summary = json.loads((folder / "summary.json").read_text())
        (folder / "summary.json").write_text(json.dumps({**summary, "resolution": res}))
    err = run("--baseline", base, method)
    assert "--resolution 128 but" in err and "not paired" in err
