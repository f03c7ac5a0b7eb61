"""The facing head (:mod:`depthnerf.model.facing_head`): the relative plane angle against closed forms, the ridge
fit against exact linear data and against itself in its two forms, the head in a weights file (round trip, a
head of another encoder refused), ``--facing auto`` taking the head's plane, and ``depthnerf fit-facing`` end to
end on a tiny mirror model."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from depthnerf.data.cameras import Intrinsics, look_at
from depthnerf.data.symmetry import facing_from_relative, facing_plane, relative_facing
from depthnerf.errors import DepthnerfError
from depthnerf.model.facing_head import (
    FacingHead,
    angle_error,
    doubled_angle,
    encoder_fingerprint,
    fit_ridge,
    head_from_tensors,
    head_tensors,
    pool_features,
)


def camera(azimuth_deg: float, elevation_deg: float, radius: float = 1.3) -> np.ndarray:
    """A z-up look-at camera at the given azimuth and elevation, looking at the origin (no roll)."""
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    eye = radius * torch.tensor([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)],
                                dtype=torch.float64)
    return look_at(eye).double().numpy()


def wrapped(estimate: float, true: float) -> float:
    """:func:`angle_error` of two floats, in float64."""
    return angle_error(torch.tensor(estimate, dtype=torch.float64), torch.tensor(true, dtype=torch.float64)).item()


@pytest.mark.parametrize("facing", [0.0, 30.0, 90.0, 135.5, 179.0])
def test_relative_angle_at_azimuth_zero_is_ninety_minus_the_facing(facing):
    """``facing_plane`` is stated for the camera at azimuth 0 (looking along -x): there psi = 90 - a, at any
    elevation (the plane is vertical, so looking down at it does not turn it)."""
    for elevation in (0.0, 20.0, 60.0):
        psi = relative_facing(facing_plane(facing), camera(0.0, elevation))
        assert wrapped(psi, 90.0 - facing) == pytest.approx(0.0, abs=1e-5)


def test_relative_angle_round_trips_for_any_camera():
    """Turning the camera 10 degrees about +z (counter-clockwise from above) turns psi by +10, and
    facing_from_relative inverts relative_facing."""
    rng = np.random.default_rng(0)
    for _ in range(50):
        facing, azimuth, elevation = rng.uniform(0, 180), rng.uniform(0, 360), rng.uniform(-60, 80)
        c2w = camera(azimuth, elevation)
        psi = relative_facing(facing_plane(facing), c2w)
        assert 0 <= psi < 180
        back = facing_from_relative(psi, c2w)
        assert wrapped(back, facing) == pytest.approx(0.0, abs=1e-5)
        turned = relative_facing(facing_plane(facing), camera(azimuth + 10.0, elevation))
        assert wrapped(turned, psi + 10.0) == pytest.approx(0.0, abs=1e-5)
    with pytest.raises(DepthnerfError, match="looks straight down"):
        facing_from_relative(10.0, np.array([[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 1], [0, 0, 0, 1.0]]))


def test_angle_error_wraps_modulo_180():
    assert wrapped(179.0, 1.0) == pytest.approx(-2.0)
    assert wrapped(1.0, 179.0) == pytest.approx(2.0)
    assert angle_error(179.0, 1.0) == pytest.approx(-2.0) and angle_error(-100.0, 80.0) == pytest.approx(0.0)
    torch.testing.assert_close(doubled_angle(torch.tensor([0.0, 90.0, 180.0])),
                               torch.tensor([[1.0, 0.0], [-1.0, 0.0], [1.0, 0.0]], dtype=torch.float64))


def linear_features(psi: torch.Tensor, channels: int, grid: int) -> torch.Tensor:
    """Pooled features that are one fixed linear function of the doubled angle of ``psi`` plus a fixed offset."""
    fixed = torch.Generator().manual_seed(100)
    mix = torch.randn(2, channels * grid * grid, generator=fixed, dtype=torch.float64)
    offset = torch.randn(channels * grid * grid, generator=fixed, dtype=torch.float64)
    return (doubled_angle(psi) @ mix + offset).float()


def linear_data(n: int, channels: int, grid: int, seed: int = 0):
    """:func:`linear_features` at ``n`` random angles (``seed``), and the angles."""
    psi = torch.rand(n, generator=torch.Generator().manual_seed(seed), dtype=torch.float64) * 180
    return linear_features(psi, channels, grid), psi


@pytest.mark.parametrize("n", [20, 200])
def test_ridge_recovers_an_exactly_linear_angle(n):
    """Features linear in (cos 2 psi, sin 2 psi): a weak ridge reads psi back to a small fraction of a degree, in
    the dual form (N < D, n = 20) and the primal one (N > D, n = 200)."""
    channels, grid = 3, 2
    x, psi = linear_data(n, channels, grid)
    head = fit_ridge(x, psi, 1e-6, channels, grid)
    maps = x.reshape(n, channels, grid, grid)
    assert angle_error(head(maps).double(), psi).abs().max().item() < 0.05
    held_x, held_psi = linear_data(10, channels, grid, seed=1)  # the same linear map at other angles
    assert angle_error(head(held_x.reshape(10, channels, grid, grid)).double(), held_psi).abs().max() < 0.05


@pytest.mark.parametrize("n", [11, 13])
def test_ridge_matches_the_other_form_of_its_solution(n):
    """D = 12 features: 11 rows are solved in the dual form, 13 in the primal; each equals the other form's
    closed solution on the same standardised, centred data."""
    channels, grid = 3, 2
    x, psi = linear_data(n, channels, grid, seed=3)
    x = x + 0.1 * torch.randn(x.shape, generator=torch.Generator().manual_seed(4))
    head = fit_ridge(x, psi, 5.0, channels, grid)
    z = (x.double() - x.double().mean(0)) / (x.double().std(0, correction=0) + 1e-6)
    y = doubled_angle(psi) - doubled_angle(psi).mean(0)
    primal = torch.linalg.solve(z.T @ z + 5.0 * torch.eye(12, dtype=z.dtype), z.T @ y)
    dual = z.T @ torch.linalg.solve(z @ z.T + 5.0 * torch.eye(n, dtype=z.dtype), y)
    torch.testing.assert_close(primal, dual)
    torch.testing.assert_close(head.weight.double(), primal, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(head.bias.double(), doubled_angle(psi).mean(0), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("n", [11, 13])
def test_ridges_share_one_gram_matrix_and_give_each_weights_head(n):
    """:func:`fit_ridges` over several weights (one Gram matrix) gives, per weight, the head :func:`fit_ridge`
    fits alone, in the dual (n = 11 < D = 12) and the primal form (n = 13)."""
    from depthnerf.model.facing_head import fit_ridges

    x, psi = linear_data(n, 3, 2)
    x = x + 0.1 * torch.randn(x.shape, generator=torch.Generator().manual_seed(3))
    lams = (0.5, 5.0, 50.0)
    heads = fit_ridges(x, psi, lams, 3, 2)
    for lam, head in zip(lams, heads, strict=True):
        torch.testing.assert_close(head.weight, fit_ridge(x, psi, lam, 3, 2).weight, rtol=0, atol=0)
    assert not torch.allclose(heads[0].weight, heads[2].weight)
    with pytest.raises(DepthnerfError, match="lambda must be a positive number, got -1"):
        fit_ridges(x, psi, (1.0, -1.0), 3, 2)


def test_confidence_is_the_length_of_the_doubled_estimate():
    """``confidence`` = |doubled|, with ``predict`` its half-angle: closed forms on a hand-set head; on exactly
    linear data a fitted head is sure of every view (|y| = 1), and the mean of two views' features whose planes are
    90 degrees apart, which a linear head maps to the mean of opposite unit vectors, has confidence 0."""
    head = FacingHead(3, 1)
    head.weight.copy_(torch.tensor([[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]]))
    pooled = torch.tensor([[0.3, 0.4, 5.0], [0.0, -2.0, 1.0]])
    torch.testing.assert_close(head.doubled(pooled), pooled[:, :2])
    torch.testing.assert_close(head.confidence(pooled), torch.tensor([0.5, 2.0]))
    expected = torch.tensor([math.degrees(math.atan2(0.4, 0.3)) / 2, 135.0])
    torch.testing.assert_close(head.predict(pooled), expected)
    maps = pooled[:, :, None, None].expand(2, 3, 4, 5)  # constant maps pool to themselves
    for got, want in zip(head.read(maps), (expected, torch.tensor([0.5, 2.0])), strict=True):
        torch.testing.assert_close(got, want)
    torch.testing.assert_close(head(maps), expected)

    channels, grid = 3, 2
    x, psi = linear_data(200, channels, grid)
    fitted = fit_ridge(x, psi, 1e-6, channels, grid)
    torch.testing.assert_close(fitted.confidence(x), torch.ones(200), atol=1e-3, rtol=0)
    between = linear_features(torch.tensor([20.0, 110.0], dtype=torch.float64), channels, grid).mean(0, keepdim=True)
    assert fitted.confidence(between).item() == pytest.approx(0.0, abs=1e-3)


def test_head_checks_its_inputs():
    head = FacingHead(channels=4, grid=2)
    with pytest.raises(DepthnerfError, match=r"expects \[B, 4, H, W\] features"):
        head(torch.zeros(1, 5, 8, 8))
    x, psi = linear_data(6, 4, 2)
    with pytest.raises(DepthnerfError, match="expected N x 16"):
        fit_ridge(x[:, :15], psi, 1.0, 4, 2)
    with pytest.raises(DepthnerfError, match="lambda must be a positive number"):
        fit_ridge(x, psi, 0.0, 4, 2)


def test_head_round_trips_through_weights_file_entries():
    x, psi = linear_data(30, 3, 2)
    head = fit_ridge(x, psi, 1.0, 3, 2, {"encoder": "abc", "lambda": 1.0})
    tensors, meta = head_tensors(head)
    back = head_from_tensors({**tensors, "encoder.x": torch.zeros(1)}, meta, "f.safetensors")
    maps = x.reshape(-1, 3, 2, 2)
    torch.testing.assert_close(back(maps), head(maps))
    assert back.describe() == head.describe() == {"grid": 2, "channels": 3, "encoder": "abc", "lambda": 1.0}
    assert head_from_tensors({"encoder.x": torch.zeros(1)}, {}, "f") is None
    with pytest.raises(DepthnerfError, match="f.safetensors: facing head tensors without a valid"):
        head_from_tensors(tensors, {}, "f.safetensors")
    tensors["facing_head.weight"] = torch.zeros(5, 2)
    with pytest.raises(DepthnerfError, match="do not match its metadata"):
        head_from_tensors(tensors, meta, "f.safetensors")


def test_checkpoint_carries_the_head_and_refuses_another_encoders(tmp_path):
    """A head saved into a weights file loads with it; a head whose encoder fingerprint is another model's is
    refused in one line naming the file; a warm start from a file with a head ignores the head."""
    from depthnerf.config_io import apply_overrides
    from depthnerf.infer.facing import fit_facing
    from depthnerf.infer.session import InferenceSession
    from depthnerf.model.pixelnerf import PixelNeRF
    from depthnerf.pretrained.load import load_pretrained
    from depthnerf.pretrained.weights import save_with_head
    from depthnerf.reconstruct.reconstructor import Reconstructor
    from depthnerf.train.warm_start import warm_start
    from tests.fixtures_checkpoints import save_tiny, tiny_config, tiny_model

    cfg = apply_overrides(tiny_config("cars", "none"), ["--model.mirror", "true"])
    path = save_tiny(tmp_path / "m.safetensors", cfg)
    model = load_pretrained(path).model
    channels = model.encoder.latent_size
    x, psi = linear_data(40, channels, 2)
    good = fit_ridge(x, psi, 1.0, channels, 2, {"encoder": encoder_fingerprint(model)})
    save_with_head(path, good, tmp_path / "h.safetensors")
    loaded = load_pretrained(tmp_path / "h.safetensors")
    assert loaded.facing_head is not None and loaded.facing_head.describe() == good.describe()
    torch.testing.assert_close(loaded.facing_head.weight, good.weight)
    assert load_pretrained(path).facing_head is None
    assert Reconstructor.from_pretrained(tmp_path / "h.safetensors").has_facing_head
    assert not Reconstructor.from_pretrained(path).has_facing_head

    other = fit_ridge(x, psi, 1.0, channels, 2, {"encoder": encoder_fingerprint(tiny_model(cfg, seed=5))})
    save_with_head(path, other, tmp_path / "bad.safetensors")
    with pytest.raises(DepthnerfError, match=r"bad.safetensors: its facing head was fitted on another encoder"):
        load_pretrained(tmp_path / "bad.safetensors")

    fresh = PixelNeRF(cfg.model, depth_aware=False)
    warm_start(fresh, str(tmp_path / "h.safetensors"), cfg.model, False)
    torch.testing.assert_close(fresh.state_dict(), model.state_dict())

    session = InferenceSession(tmp_path / "h.safetensors")
    image = torch.rand(1, 3, 16, 16)
    intr = Intrinsics(focal=16.4, cx=8.0, cy=8.0, height=16, width=16)
    c2w = torch.from_numpy(camera(0.0, 20.0)).float()
    encoded = session.encode(image, torch.ones(1, 16, 16, dtype=torch.bool), c2w, intr)
    fit = fit_facing(session, encoded, min_confidence=0.0)
    pooled = pool_features(encoded.enc.features[0, :1], 2)
    psi_head, sure = float(good.predict(pooled)[0]), float(good.confidence(pooled)[0])
    assert fit.facing == fit.best == fit.start == pytest.approx(facing_from_relative(psi_head, c2w.numpy()))
    assert len(fit.errors) == 1 and fit.as_dict()["head"] == fit.start and fit.as_dict()["tried"] == 1
    assert fit.confidence == fit.as_dict()["head_confidence"] == pytest.approx(sure)
    # the gate: no plane below the threshold (the head's reading kept as ``best``), the head's plane at or above
    unsure = fit_facing(session, encoded, min_confidence=sure * 1.01)
    assert unsure.facing is None and unsure.best == unsure.start == fit.best and unsure.confidence == fit.confidence
    assert fit_facing(session, encoded, min_confidence=sure * 0.99).facing == fit.facing
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(DepthnerfError, match="--facing-min-confidence must be a number >= 0"):
            fit_facing(session, encoded, min_confidence=bad)
    rec = Reconstructor(session)
    _, line = rec.symmetry(unsure.facing, unsure, sure * 1.01)
    assert line.startswith("off: the checkpoint's facing head is unsure of the facing (confidence")
    _, line = rec.symmetry(fit.facing, fit, 0.0)
    assert line.startswith(f"on: the object faces {fit.facing:g} degrees (--facing auto: the checkpoint's facing "
                           f"head, confidence {sure:.2f}")


def test_fit_facing_command_end_to_end(tmp_path, capsys):
    """``depthnerf fit-facing`` on a tiny mirror model and a fixture dataset writes a checkpoint that loads with a
    head of this encoder, prints the held-out errors, and refuses nonsense flags and non-mirror models."""
    import json

    from depthnerf.cli import main
    from depthnerf.config_io import apply_overrides
    from depthnerf.pretrained.load import load_pretrained
    from tests.fixtures_checkpoints import save_tiny, tiny_config
    from tests.fixtures_srn import make_srn_fixture

    root = make_srn_fixture(tmp_path / "data", "cars", splits={"train": 6}, views=4, size=16)
    path = save_tiny(tmp_path / "m.safetensors", apply_overrides(tiny_config("cars", "none"),
                                                                 ["--model.mirror", "true"]))
    out = tmp_path / "with-head.safetensors"
    assert main(["fit-facing", "--checkpoint", str(path), "--data", str(root), "--category", "cars",
                 "--views-per-object", "3", "--grid", "2", "--out", str(out), "--json", str(tmp_path / "s.json")]) == 0
    printed = capsys.readouterr().out
    assert "<- chosen" in printed and f"wrote {out}" in printed
    loaded = load_pretrained(out)
    info = loaded.facing_head.describe()
    assert info["views"] == 18 and info["objects"] == 6 and info["grid"] == 2 and info["inputs"] == "both"
    assert info["encoder"] == encoder_fingerprint(loaded.model)
    scores = json.loads((tmp_path / "s.json").read_text())
    assert set(scores["validation"]) == {"10", "100", "1000", "10000"} and scores["head"] == info

    from fixtures_scripts import load_script

    errors = load_script("facing_head_error")  # the head's error on a split, as scripts/facing_head_error.py reports it
    assert errors.main(["--checkpoint", str(out), "--data", str(root), "--category", "cars", "--split", "train",
                        "--views-per-object", "2", "--json", str(tmp_path / "e.json")]) == 0
    report = json.loads((tmp_path / "e.json").read_text())[str(out)]
    assert report["views"] == 12 and 0.0 <= report["median_deg"] <= report["p90_deg"] <= 90.0
    assert 0.0 <= report["unsure"] <= 1.0 and (report["unsure_median_deg"] is None) == (report["unsure"] == 0.0)
    assert "12 views, |angle error| median" in capsys.readouterr().out
    gate = load_script("facing_gate_study")  # the head's plane against none, by the head's confidence
    assert gate.main(["--checkpoint", str(out), "--data", str(root), "--category", "cars", "--split", "train",
                      "--objects", "2", "--views-per-object", "2", "--views-stride", "20", "--thresholds", "0", "1e9",
                      "--json", str(tmp_path / "g.json")]) == 0
    written = json.loads((tmp_path / "g.json").read_text())
    cases = written["cases"]
    assert written["settings"]["views_stride"] == 20 and len(cases) == 4 and all(set(c["psnr"]) == {"true", "head", "none"} for c in cases)
    printed = capsys.readouterr().out
    assert "4 cases, 2 objects" in printed and "\n0 | 0/4 | +0.00" in printed and "\n1e+09 | 4/4 |" in printed
    none_minus_head = np.mean([c["psnr"]["none"] - c["psnr"]["head"] for c in cases])
    assert f"\n1e+09 | 4/4 | {none_minus_head:+.2f}" in printed  # every case gated: no plane's PSNR
    gate_args = ["--checkpoint", str(out), "--data", str(root), "--category", "cars", "--split", "train",
                 "--objects", "2", "--views-per-object", "2", "--thresholds", "0", "--json", str(tmp_path / "g.json")]
    assert gate.main([*gate_args, "--views-stride", "20"]) == 0  # every case found in the file: nothing rendered
    resumed = capsys.readouterr()
    assert "resuming: 4 cases from" in resumed.err and "confidence" not in resumed.err
    assert "4 cases, 2 objects" in resumed.out
    written["cases"] = cases[:3]  # a run stopped after its third case renders the fourth only, to the same scores
    (tmp_path / "g.json").write_text(json.dumps(written))
    assert gate.main([*gate_args, "--views-stride", "20"]) == 0
    assert capsys.readouterr().err.count("confidence") == 1
    again = json.loads((tmp_path / "g.json").read_text())["cases"]
    assert again[:3] == cases[:3] and again[3]["psnr"] == pytest.approx(cases[3]["psnr"], abs=1e-4)
    assert gate.main([*gate_args, "--views-stride", "10"]) == 2
    assert "holds cases of views_stride 20, this run has 10" in capsys.readouterr().err
    (tmp_path / "old.json").write_text(json.dumps(cases))  # a plain list of cases: reported, never resumed
    assert gate.main(["--checkpoint", "x", "--data", "x", "--category", "cars", "--from-json", str(tmp_path / "g.json"),
                      str(tmp_path / "old.json"), "--thresholds", "0"]) == 0
    assert "8 cases, 2 objects" in capsys.readouterr().out
    assert gate.main(["--checkpoint", str(out), "--data", str(root), "--category", "cars", "--split", "train",
                      "--objects", "1", "--views-per-object", "1", "--views-stride", "20", "--inputs", "photo",
                      "--json", str(tmp_path / "p.json")]) == 0  # framed as a photo, rendered from its camera
    framed = json.loads((tmp_path / "p.json").read_text())["cases"][0]
    first = next(c for c in cases if c["object"] == framed["object"] and c["view"] == framed["view"])
    assert framed["confidence"] != pytest.approx(first["confidence"])  # the framing moves the features it reads
    assert "1 cases, 1 objects" in capsys.readouterr().out
    assert errors.main(["--checkpoint", str(out), "--data", str(root), "--category", "cars", "--split", "train",
                        "--objects", "2", "--views-per-object", "1", "--photo"]) == 0  # through reconstruct
    assert "2 views, |angle error| median" in capsys.readouterr().out
    with pytest.raises(SystemExit):  # reconstruct frames each photo itself
        errors.main(["--checkpoint", str(out), "--data", str(root), "--category", "cars", "--photo", "--inputs",
                     "photo"])
    assert "--photo gives each view to reconstruct, which frames it itself" in capsys.readouterr().err
    assert errors.main(["--checkpoint", str(path), "--data", str(root), "--category", "cars", "--split", "train"]) == 2
    assert "carries no facing head" in capsys.readouterr().err
    assert main(["fit-facing", "--checkpoint", str(path), "--data", str(root), "--category", "cars",
                 "--views-per-object", "3", "--grid", "2", "--inputs", "photo", "--out", str(out), "--overwrite"]) == 0
    info = load_pretrained(out).facing_head.describe()
    assert info["views"] == 18 and info["inputs"] == "photo"
    assert main(["fit-facing", "--checkpoint", str(path), "--data", str(root), "--category", "cars",
                 "--grid", "0", "--out", str(out)]) == 2
    assert "--grid must be >= 1, got 0" in capsys.readouterr().err
    plain = save_tiny(tmp_path / "plain.safetensors", tiny_config("cars", "none"))
    assert main(["fit-facing", "--checkpoint", str(plain), "--data", str(root), "--category", "cars",
                 "--out", str(out), "--overwrite"]) == 2
    assert "not a mirror model" in capsys.readouterr().err


def test_photo_inputs_encode_a_view_as_reconstruct_encodes_it_as_a_photo(tmp_path):
    """``fit-facing --inputs both``: each drawn view gives two rows, the first the dataset view's features (as
    ``--inputs dataset`` gathers them) and the second the features ``reconstruct`` computes from that view given as
    an RGBA photo (recentred and scaled to the model's fill), so a head fitted on them reads what a photo shows."""
    from depthnerf.config_io import apply_overrides
    from depthnerf.model.facing_head import pool_features
    from depthnerf.reconstruct.photo import prepare_photo
    from depthnerf.reconstruct.reconstructor import Reconstructor
    from depthnerf.train.facing_head import FacingHeadConfig, dataset_session, drawn_views, gather
    from tests.fixtures_checkpoints import save_tiny, tiny_config
    from tests.fixtures_srn import make_srn_fixture

    root = make_srn_fixture(tmp_path / "data", "cars", splits={"train": 3}, views=4, size=16)
    path = save_tiny(tmp_path / "m.safetensors", apply_overrides(tiny_config("cars", "none"),
                                                                 ["--model.mirror", "true"]))
    base = FacingHeadConfig(data=root, category="cars", objects=3, views_per_object=2, grid=2, inputs="dataset")
    rows = {}
    for inputs in ("dataset", "both"):
        cfg = dataclasses.replace(base, inputs=inputs)
        session, records = dataset_session(path, cfg)
        rows[inputs] = gather(session, cfg, records)
    (dx, dpsi, down), (bx, bpsi, bown) = rows["dataset"], rows["both"]
    assert bx.shape[0] == 2 * dx.shape[0] == 12
    torch.testing.assert_close(bx[0::2], dx)
    torch.testing.assert_close(bpsi[0::2], dpsi) and torch.testing.assert_close(bpsi[1::2], dpsi)
    assert (bown[0::2] == down).all() and (bown[1::2] == down).all()
    rec = Reconstructor.from_pretrained(path)
    photo_rows = []
    for record, picks in zip(records, drawn_views(records, base), strict=True):
        for view in picks:
            src = rec.session.load_views(record, [view], 16)
            rgba = np.dstack([src.images[0].permute(1, 2, 0).numpy(), src.masks[0].numpy()]).astype(np.float32)
            prepared = prepare_photo(rgba, None, 16, "auto", rec.default_fill)
            encoded = rec.encode_view(torch.from_numpy(prepared.image).permute(2, 0, 1)[None].contiguous(),
                                      torch.from_numpy(prepared.mask)[None], src.poses[0], src.intrinsics)
            photo_rows.append(pool_features(encoded.enc.features[0, :1], 2))
    assert not torch.allclose(bx[1::2], dx)  # framing moved the object: the features differ
    torch.testing.assert_close(bx[1::2], torch.cat(photo_rows))
    with pytest.raises(DepthnerfError, match="--inputs must be one of dataset, photo, both, got 'photos'"):
        FacingHeadConfig(data=root, category="cars", inputs="photos")


def test_export_carries_a_head_fitted_on_the_runs_encoder(tmp_path):
    """``scripts/export_checkpoint.py --facing-head``: the fp16 export loads with the head and its cards describe
    it; a head fitted on another encoder is refused before anything takes the shipped name."""
    from fixtures_scripts import load_script

    from depthnerf.config_io import apply_overrides
    from depthnerf.pretrained.load import load_pretrained
    from depthnerf.pretrained.weights import save_with_head
    from tests.fixtures_checkpoints import tiny_config, tiny_model, tiny_run

    exporter = load_script("export_checkpoint")
    cfg = apply_overrides(tiny_config("cars", "none"), ["--model.mirror", "true"])
    run = tiny_run(tmp_path / "run", cfg)
    source = load_pretrained(run)
    channels = source.model.encoder.latent_size
    x, psi = linear_data(40, channels, 2)
    info = {"encoder": encoder_fingerprint(source.model), "lambda": 10.0, "views": 40, "objects": 10,
            "data": "d/cars_train", "validation_median_deg": 1.5, "validation_p90_deg": 4.0}
    save_with_head(source.path, fit_ridge(x, psi, 10.0, channels, 2, info), tmp_path / "head.safetensors")
    ship = tmp_path / "ship"
    res = exporter.export(run, "cpu-cars-mirror", ship, facing_head=tmp_path / "head.safetensors",
                          facing_command="depthnerf fit-facing --checkpoint run --data d --category cars --out h")
    exported = load_pretrained(res.weights)
    assert exported.facing_head is not None and exported.facing_head.describe() == {"grid": 2, "channels": channels,
                                                                                    **info}
    assert res.card["facing_head"]["command"].startswith("depthnerf fit-facing")
    text = res.card_md.read_text()
    assert "## Facing head" in text and "median angle error 1.50 degrees" in text and "--facing-head HEAD" in text

    other = tiny_model(cfg, seed=9)
    wrong = {**info, "encoder": encoder_fingerprint(other)}
    save_with_head(source.path, fit_ridge(x, psi, 10.0, channels, 2, wrong), tmp_path / "wrong.safetensors")
    before = res.weights.read_bytes()
    with pytest.raises(DepthnerfError, match="--facing-head .*wrong.safetensors: its facing head was fitted on another encoder"):
        exporter.export(run, "cpu-cars-mirror", ship, facing_head=tmp_path / "wrong.safetensors")
    with pytest.raises(DepthnerfError, match="carries no facing head"):
        exporter.export(run, "cpu-cars-mirror", ship, facing_head=source.path)
    assert res.weights.read_bytes() == before
