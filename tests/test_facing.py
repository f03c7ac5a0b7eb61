"""``--facing auto`` (:mod:`depthnerf.infer.facing`) and ``--schedule.mirror_jitter`` (the planes a little off that
training can show a mirror model): the search against closed forms and brute force, the error a render is scored
by, the plane swapped into encoded views, and reconstruct end to end on a tiny mirror model."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from depthnerf.data.symmetry import facing_plane
from depthnerf.errors import DepthnerfError
from depthnerf.infer.facing import AUTO, facing_error, search_facing, with_plane
from depthnerf.train.items import jittered_plane


def wrapped(a: float, b: float) -> float:
    """Signed difference of two facings modulo 180 degrees, in [-90, 90)."""
    return (a - b + 90.0) % 180.0 - 90.0


@pytest.mark.parametrize("truth", [37.3, 0.4, 179.6, 90.0, 121.85])
def test_search_finds_the_minimum_of_a_parabola_exactly(truth):
    """A quadratic in the wrapped angle: the coarse and fine passes land next to the minimum, and the parabola's
    vertex is the minimum itself (wrap-around at 0 / 180 included)."""
    fit = search_facing(lambda a: 1.0 if a is None else 1e-3 * wrapped(a, truth) ** 2)
    assert fit.facing == pytest.approx(truth % 180, abs=1e-9) and fit.best == fit.facing
    assert fit.error == pytest.approx(0.0, abs=1e-12) and fit.none_error == 1.0
    assert all(0 <= a < 180 for a in fit.errors)


def test_search_matches_brute_force_on_a_bumpy_curve():
    """A curve with one wide basin and ripples: the search ends within a degree of a 0.05-degree brute-force grid's
    minimum, after about 30 evaluations instead of 3600, each facing evaluated once."""
    calls: list[float | None] = []

    def error(a):
        calls.append(a)
        if a is None:
            return 10.0
        d = math.radians(wrapped(a, 64.0))
        return 1.0 - math.cos(2 * d) + 0.02 * math.sin(7 * d) ** 2

    fit = search_facing(error)
    grid = np.arange(0, 180, 0.05)
    brute = grid[np.argmin([error(a) for a in grid])]
    assert abs(wrapped(fit.best, brute)) <= 1.0
    searched = calls[:len(fit.errors) + 1]
    assert len(searched) == len(set(searched)) <= 32 and searched[-1] is None


def test_no_plane_wins_when_it_renders_the_input_view_better():
    fit = search_facing(lambda a: 0.5 if a is None else 1.0 + 1e-3 * wrapped(a, 20.0) ** 2)
    assert fit.facing is None and fit.best == pytest.approx(20.0) and fit.none_error == 0.5
    assert fit.as_dict() == {"facing": None, "best": fit.best, "error": fit.error, "none_error": 0.5,
                             "tried": len(fit.errors), "head": None, "head_confidence": None}
    with pytest.raises(DepthnerfError, match="coarse_step must divide 180"):
        search_facing(lambda a: 0.0, coarse_step=7)


def test_facing_error_scores_the_render_against_the_area_averaged_photo():
    """A fake renderer that draws the photo exactly (at the asked size) for the plane of facing 37 and a uniform
    shift growing with the angle otherwise: the error is the shift squared, so the search finds 37."""
    photo = torch.rand(3, 8, 8)
    small = torch.nn.functional.avg_pool2d(photo[None], 2)[0].permute(1, 2, 0)

    def render(plane, side):
        assert side == 4
        if plane is None:
            return small + 0.3
        angle = math.degrees(math.atan2(-plane[0], plane[1])) % 180
        return small + 0.01 * wrapped(angle, 37.0)

    error = facing_error(render, photo, scale=2)
    assert error(37.0) == pytest.approx(0.0, abs=1e-12)
    assert error(47.0) == pytest.approx(0.01, rel=1e-5) and error(None) == pytest.approx(0.09, rel=1e-5)
    assert search_facing(error).facing == pytest.approx(37.0, abs=1e-3)
    with pytest.raises(DepthnerfError, match="scale 3 must divide"):
        facing_error(render, photo, scale=3)


def test_with_plane_swaps_the_plane_and_shares_the_features():
    from depthnerf.model.pixelnerf import EncodedViews

    enc = EncodedViews(features=torch.rand(1, 1, 4, 2, 2), w2c=torch.eye(4)[None, None],
                       focal=torch.ones(1, 1), principal=torch.zeros(1, 1, 2), image_size=(4, 4),
                       symmetry_plane=torch.tensor([[0.0, 1.0, 0.0, 0.0]]))
    turned = with_plane(enc, facing_plane(90.0))
    assert turned.features is enc.features
    torch.testing.assert_close(turned.symmetry_plane, torch.tensor([facing_plane(90.0)]))
    assert with_plane(enc, None).symmetry_plane.tolist() == [[0.0, 0.0, 0.0, 0.0]]


@pytest.mark.parametrize("plane", [(0.0, 1.0, 0.0, 0.0), (0.6, 0.0, 0.8, 0.25)])
def test_jittered_planes_turn_about_an_axis_in_the_plane(plane):
    """Each turned plane has a unit normal at most ``max`` degrees from the original, still holds the plane's point
    ``d n`` (it turned about an axis through it), and the angles fill [0, max] as a uniform draw does."""
    gen = torch.Generator().manual_seed(3)
    n, d = np.array(plane[:3]), plane[3]
    angles = []
    for _ in range(4000):
        turned = jittered_plane(plane, 10.0, gen)
        m = np.array(turned[:3])
        assert np.linalg.norm(m) == pytest.approx(1.0, abs=1e-12)
        assert m @ (d * n) == pytest.approx(turned[3], abs=1e-12)
        angles.append(math.degrees(math.acos(min(1.0, float(m @ n)))))
    angles = np.array(angles)
    assert angles.max() <= 10.0 + 1e-9 and abs(angles.mean() - 5.0) < 0.2
    assert abs((angles < 5.0).mean() - 0.5) < 0.04


def test_mirror_jitter_changes_only_the_plane_of_a_training_item(tmp_path):
    """Items drawn with and without jitter have the same views and rays (the plane is drawn last); the planes
    differ by at most the jitter, and dropped items still carry the zero plane."""
    from depthnerf.data.srn import index_split
    from depthnerf.depth.prior import PriorConfig, open_prior
    from depthnerf.train.batching import ItemKey
    from depthnerf.train.items import TrainItems
    from tests.fixtures_srn import make_srn_fixture

    root = make_srn_fixture(tmp_path / "data", "cars", splits={"train": 2}, views=4, size=16)
    records = index_split(root, "cars", "train").objects
    source = open_prior(PriorConfig(estimator="none"))
    plane = (0.0, 1.0, 0.0, 0.0)
    common = dict(resolution=16, target_views=1, rays_per_object=8, target_priors=False, symmetry_plane=plane,
                  mirror_dropout=0.3)
    exact, turned = TrainItems(records, source, **common), TrainItems(records, source, mirror_jitter=15.0, **common)
    for seed in range(40):
        key = ItemKey(object_index=seed % 2, seed=seed, sources=1, use_bbox=False)
        a, b = exact[key], turned[key]
        torch.testing.assert_close(a.ray_dirs, b.ray_dirs, rtol=0, atol=0)
        torch.testing.assert_close(a.target_rgb, b.target_rgb, rtol=0, atol=0)
        pa, pb = a.source.symmetry_plane[0].double(), b.source.symmetry_plane[0].double()
        if pa.abs().sum() == 0:
            assert pb.abs().sum() == 0
        else:
            assert math.degrees(math.acos(min(1.0, float(pa[:3] @ pb[:3])))) <= 15.0 + 1e-4


def test_mirror_jitter_flag_is_checked():
    from depthnerf.config_io import apply_overrides
    from depthnerf.train.config import check_config
    from tests.fixtures_checkpoints import tiny_config

    cfg = tiny_config("cars", "none")
    for value, message in (("-1", "must be >= 0"), ("nan", "must be >= 0"),
                           ("91", "must be an angle in \\[0, 90\\] degrees")):
        with pytest.raises(DepthnerfError, match=f"--schedule.mirror_jitter {message}"):
            check_config(apply_overrides(cfg, ["--schedule.mirror_jitter", value]))


def test_reconstruct_facing_auto_is_the_estimate_applied(tmp_path, capsys):
    """``facing="auto"`` on a tiny mirror model: the manifest's settings hold the estimate, and the views are
    exactly those of the same photo reconstructed with the chosen facing given (or none)."""
    from PIL import Image

    from depthnerf.cli import main
    from depthnerf.config_io import apply_overrides
    from depthnerf.reconstruct.reconstructor import ReconstructConfig, Reconstructor
    from tests.fixtures_checkpoints import save_tiny, tiny_config

    path = save_tiny(tmp_path / "mirror.safetensors",
                     apply_overrides(tiny_config("cars", "none"), ["--model.mirror", "true"]))
    photo = np.full((40, 40, 3), 255, np.uint8)
    photo[12:30, 8:34] = (200, 40, 40)
    Image.fromarray(photo).save(tmp_path / "car.png")
    rec = Reconstructor.from_pretrained(path)
    auto = rec.reconstruct(tmp_path / "car.png", config=ReconstructConfig(views=2, mesh_resolution=0, facing=AUTO))
    fit = auto.settings["facing_fit"]
    assert fit["tried"] >= 28 and auto.settings["facing"] == fit["facing"] and 0 <= fit["best"] < 180
    given = rec.reconstruct(tmp_path / "car.png",
                            config=ReconstructConfig(views=2, mesh_resolution=0, facing=fit["facing"]))
    np.testing.assert_array_equal(auto.views, given.views)
    assert auto.settings["symmetry_plane"] == given.settings["symmetry_plane"]
    assert "--facing auto" in auto.settings["symmetry"] and "facing_s" in auto.timings
    assert main(["reconstruct", str(tmp_path / "car.png"), "--checkpoint", str(path), "--out", str(tmp_path / "o"),
                 "--views", "2", "--mesh-resolution", "0", "--facing", "auto", "--no-progress"]) == 0
    assert "(--facing auto: input-view error" in capsys.readouterr().out or fit["facing"] is None
    with pytest.raises(DepthnerfError, match="--facing must be a finite angle in degrees, 'auto' or 'none'"):
        ReconstructConfig(facing="sideways")
    for bad in (-1.0, float("nan"), True, "0.4"):
        with pytest.raises(DepthnerfError, match="--facing-min-confidence must be a number >= 0"):
            ReconstructConfig(facing=AUTO, facing_min_confidence=bad)
    assert main(["reconstruct", str(tmp_path / "car.png"), "--checkpoint", str(path), "--out", str(tmp_path / "o2"),
                 "--facing", "auto", "--facing-min-confidence", "-1", "--no-progress"]) == 2
    assert capsys.readouterr().err.strip() == "error: --facing-min-confidence must be a number >= 0, got -1.0"
    assert not (tmp_path / "o2").exists()
