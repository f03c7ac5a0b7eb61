"""Mirror-symmetric conditioning: the plane convention, the data's symmetry, the no-plane mode, and the training
items' plane draws (the field against a brute-force loop: tests/test_pixels_at_point.py)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
import trimesh

from depthnerf.data.symmetry import (
    SHAPENET_PLANE,
    dataset_plane,
    facing_plane,
    plane_from_card,
    reflect_dirs,
    reflect_points,
)
from depthnerf.data.synth.cars import CAR_STYLES, build_car, sample_car
from depthnerf.data.synth.chairs import CHAIR_ARCHETYPES, build_chair, sample_chair
from depthnerf.errors import DepthnerfError
from depthnerf.model import PixelNeRF
from tests.test_model import query, randomize, small_config, sources

SYNTH_CARD = {"objects": {"bbox_diagonal": 1.0, "centre": [0.0, 0.0, 0.0], "front": "+x", "up": "+z"}}


def test_dataset_plane_sources(tmp_path):
    assert plane_from_card(SYNTH_CARD, "card") == (0.0, 1.0, 0.0, 0.0)  # left axis = up x front = +y
    shifted = {"objects": {"front": "-y", "up": "+z", "centre": [0.5, 0.2, 0.0]}}
    assert plane_from_card(shifted, "card") == pytest.approx((1.0, 0.0, 0.0, 0.5))  # normal +x through x = 0.5
    assert plane_from_card({"mirror_plane": [0, 0, 2, 1]}, "card") == (0.0, 0.0, 1.0, 0.5)
    assert plane_from_card({"objects": {}}, "card") is None
    with pytest.raises(DepthnerfError, match="parallel"):
        plane_from_card({"objects": {"front": "+z", "up": "-z"}}, "card")
    plane, source = dataset_plane(tmp_path, "cars")
    assert plane == SHAPENET_PLANE and "ShapeNet" in source  # no card: SRN / ShapeNet data
    assert SHAPENET_PLANE == (1.0, 0.0, 0.0, 0.0)  # x = 0: ShapeNet's left-right axis is X (module docstring)
    (tmp_path / "cars_card.json").write_text(json.dumps(SYNTH_CARD))
    assert dataset_plane(tmp_path, "cars") == ((0.0, 1.0, 0.0, 0.0), "dataset card cars_card.json")
    assert dataset_plane(tmp_path, "cars", (0, 0, 3, 0))[0] == (0.0, 0.0, 1.0, 0.0)
    with pytest.raises(DepthnerfError, match="--data.symmetry_plane: a symmetry plane is 4 finite numbers"):
        dataset_plane(tmp_path, "cars", (0, 0, 0, 1))
    (tmp_path / "cars_card.json").write_text("{not json")
    with pytest.raises(DepthnerfError, match="cars_card.json: unreadable dataset card"):
        dataset_plane(tmp_path, "cars")


@pytest.mark.parametrize("card, said", [
    ({"mirror_plane": "abc"}, " mirror_plane: a symmetry plane is 4 finite numbers"),
    ({"mirror_plane": 5}, " mirror_plane: a symmetry plane is 4 finite numbers"),
    ({"mirror_plane": [0, 1, 0, "x"]}, " mirror_plane: a symmetry plane is 4 finite numbers"),
    ({"objects": [1]}, ": objects must be a JSON object"),
    ({"objects": {"front": ["+x"], "up": "+z"}}, ": objects.front / objects.up must be one of"),
    ({"objects": {"front": "+x", "up": "+z", "centre": [1, 2]}}, ": objects.centre must be 3 finite numbers"),
    ({"objects": {"front": "+x", "up": "+z", "centre": "origin"}}, ": objects.centre must be 3 finite numbers"),
])
def test_a_malformed_card_plane_is_one_line_naming_the_card(tmp_path, card, said):
    """Each of these was a ValueError, TypeError or AttributeError traceback out of ``train --model.mirror``."""
    path = tmp_path / "cars_card.json"
    path.write_text(json.dumps(card))
    with pytest.raises(DepthnerfError, match=f"^{path}{said}"):
        dataset_plane(tmp_path, "cars")


def test_reflection_formulas():
    plane = torch.tensor([[0.6, 0.8, 0.0, 0.3], [0.0, 0.0, 0.0, 0.0]])
    pts = torch.randn(2, 7, 3, dtype=torch.float64).float()
    mirrored = reflect_points(pts, plane)
    n, d = plane[0, :3], plane[0, 3]
    for p, q in zip(pts[0], mirrored[0], strict=True):
        assert float(q @ n - d) == pytest.approx(-float(p @ n - d), abs=1e-5)  # opposite side, same distance
        assert torch.allclose((p + q) / 2 @ n, d, atol=1e-5)  # midpoint on the plane
    torch.testing.assert_close(reflect_points(mirrored, plane), pts)  # an involution
    torch.testing.assert_close(mirrored[1], pts[1])  # the zero plane: unchanged
    dirs = torch.nn.functional.normalize(torch.randn(2, 5, 3), dim=-1)
    torch.testing.assert_close(reflect_dirs(dirs, plane)[0] @ n, -(dirs[0] @ n))
    # facing: 0 = towards the camera at azimuth 0 (+x): the plane holds +x; facing 90 holds +y
    assert facing_plane(0.0) == pytest.approx((0.0, 1.0, 0.0, 0.0), abs=1e-12)
    assert facing_plane(90.0) == pytest.approx((-1.0, 0.0, 0.0, 0.0), abs=1e-12)
    assert facing_plane(30.0) == pytest.approx(tuple(-v for v in facing_plane(210.0)), abs=1e-12)


def test_has_plane_reads_the_normal_only():
    """An object has a plane exactly when its normal is non-zero; a zero normal with a non-zero offset is no
    plane (the reflections leave points unchanged there, so the mirror branch must stay off)."""
    from depthnerf.data.symmetry import has_plane

    plane = torch.tensor([[0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.7], [0.0, 0.0, -1.0, 0.0], [0.6, 0.8, 0.0, -2.0]])
    assert has_plane(plane).tolist() == [0.0, 0.0, 1.0, 1.0]
    pts = torch.randn(4, 3, 3)
    torch.testing.assert_close(reflect_points(pts, plane)[1], pts[1])


def _mirror_gap(mesh_vertices: np.ndarray, faces: np.ndarray, plane: tuple[float, ...]) -> np.ndarray:
    """Distance from the mirror images of surface samples to the surface."""
    mesh = trimesh.Trimesh(mesh_vertices, faces)
    pts, _ = trimesh.sample.sample_surface(mesh, 1500, seed=0)
    mirrored = reflect_points(torch.tensor(pts)[None], torch.tensor([plane], dtype=torch.float64))[0].numpy()
    return trimesh.proximity.closest_point(mesh, mirrored)[1]


@pytest.mark.parametrize(("category", "name"), [("cars", s) for s in CAR_STYLES]
                         + [("chairs", a) for a in CHAIR_ARCHETYPES])
def test_synthetic_objects_are_unchanged_by_their_card_plane(category, name):
    """The plane derived from the synthetic card maps every generated object onto itself (office chairs only
    nearly: their five-star base has a random phase and, as in ShapeNet, objects are centred on their bounding
    box, so the base also shifts the symmetric rest off the plane by a few thousandths)."""
    plane = plane_from_card(SYNTH_CARD, "card")
    build, sample = (build_car, sample_car) if category == "cars" else (build_chair, sample_chair)
    mesh = build(sample(np.random.default_rng(3), name))
    gap = _mirror_gap(mesh.vertices, mesh.faces, plane)
    wrong = _mirror_gap(mesh.vertices, mesh.faces, (1.0, 0.0, 0.0, 0.0))  # the front-back plane
    if name == "office":
        assert gap.mean() < 0.01 and wrong.mean() > 2 * gap.mean()
    else:
        assert np.quantile(gap, 0.99) < 3e-3 and gap.mean() < 3e-4  # facets
        assert wrong.mean() > 5e-3


def test_no_plane_is_the_plain_model_and_the_branch_trains():
    torch.manual_seed(0)
    cfg = small_config()
    cfg.mirror = True
    mirror = randomize(PixelNeRF(cfg, depth_aware=False))
    plain = PixelNeRF(small_config(), depth_aware=False).eval()
    missing = plain.load_state_dict(mirror.state_dict(), strict=False)
    assert missing.missing_keys == [] and all("mirror" in k for k in missing.unexpected_keys)
    src = sources(b=2, v=1, size=32)
    pts, dirs = query(b=2)
    with torch.no_grad():
        expected = plain.field(plain.encode(src), "fine")(pts, dirs)
        for plane in (None, torch.zeros(2, 4)):
            src.symmetry_plane = plane
            got = mirror.field(mirror.encode(src), "fine")(pts, dirs)
            torch.testing.assert_close(got, expected, rtol=0, atol=0)
    src.symmetry_plane = torch.tensor([[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]])
    with torch.no_grad():
        with_plane = mirror.field(mirror.encode(src), "fine")(pts, dirs)
    assert not torch.allclose(with_plane[1][0], expected[1][0])  # object 0 uses its plane
    torch.testing.assert_close(with_plane[1][1], expected[1][1])  # object 1 has none
    mirror.train()
    rgb, sigma = mirror.field(mirror.encode(src), "coarse")(pts, dirs)
    (rgb.sum() + sigma.sum()).backward()
    assert mirror.coarse.lin_in_mirror.weight.grad.abs().sum() > 0
    assert all(lin.weight.grad.abs().sum() > 0 for lin in mirror.coarse.lin_z_mirror)


def test_symmetry_plane_shape_is_checked():
    cfg = small_config()
    cfg.mirror = True
    src = sources(b=2)
    src.symmetry_plane = torch.zeros(1, 4)
    with pytest.raises(DepthnerfError, match=r"SourceViews.symmetry_plane must have shape \[2, 4\]"):
        PixelNeRF(cfg, depth_aware=False).encode(src)


def test_training_items_draw_the_plane_last(tmp_path):
    """A mirror run sees the same views and rays as a plain run; about ``mirror_dropout`` of its items carry the
    zero plane, the same ones on every call."""
    from depthnerf.data.srn import index_split
    from depthnerf.depth.prior import PriorConfig, open_prior
    from depthnerf.train.batching import ItemKey
    from depthnerf.train.items import TrainItems
    from tests.fixtures_srn import make_srn_fixture

    make_srn_fixture(tmp_path, "cars", splits={"train": 2}, views=4, size=16)
    records = index_split(tmp_path, "cars", "train").objects
    prior = open_prior(PriorConfig("none"), data_root=tmp_path, resolution=16, records=records)
    common = dict(resolution=16, target_views=0, rays_per_object=8, target_priors=False)
    plain = TrainItems(records, prior, **common)
    mirror = TrainItems(records, prior, **common, symmetry_plane=(0.0, 1.0, 0.0, 0.0), mirror_dropout=0.3)
    keys = [ItemKey(object_index=k % 2, seed=1000 + k, use_bbox=False) for k in range(200)]
    dropped = 0
    for key in keys:
        a, b = plain[key], mirror[key]
        assert a.source.symmetry_plane is None
        torch.testing.assert_close(a.ray_dirs, b.ray_dirs, rtol=0, atol=0)
        torch.testing.assert_close(a.target_rgb, b.target_rgb, rtol=0, atol=0)
        plane = b.source.symmetry_plane[0].tolist()
        assert plane in ([0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0])
        dropped += plane == [0.0, 0.0, 0.0, 0.0]
        assert mirror[key].source.symmetry_plane[0].tolist() == plane
    assert abs(dropped / len(keys) - 0.3) < 4 * math.sqrt(0.3 * 0.7 / len(keys))


def test_reconstruct_facing_sets_the_plane(tmp_path, capsys):
    """A mirror checkpoint gets the plane of ``--facing`` (and none with ``none``); a plain one ignores it."""
    import numpy as np
    from PIL import Image

    from depthnerf.cli import main
    from depthnerf.config_io import apply_overrides
    from depthnerf.reconstruct.reconstructor import ReconstructConfig, Reconstructor
    from tests.fixtures_checkpoints import save_tiny, tiny_config

    plain_cfg = tiny_config("cars", "none")
    mirror_cfg = apply_overrides(plain_cfg, ["--model.mirror", "true"])
    mirror_path = save_tiny(tmp_path / "mirror.safetensors", mirror_cfg)
    plain_path = save_tiny(tmp_path / "plain.safetensors", plain_cfg)
    photo = np.full((40, 40, 3), 255, np.uint8)
    photo[12:30, 8:34] = (200, 40, 40)
    Image.fromarray(photo).save(tmp_path / "car.png")
    cfg = ReconstructConfig(views=2, mesh_resolution=0)
    mirror = Reconstructor.from_pretrained(mirror_path)
    side = mirror.reconstruct(tmp_path / "car.png", config=cfg)
    front = mirror.reconstruct(tmp_path / "car.png", config=ReconstructConfig(views=2, mesh_resolution=0, facing=0))
    off = mirror.reconstruct(tmp_path / "car.png", config=ReconstructConfig(views=2, mesh_resolution=0, facing=None))
    assert side.settings["symmetry_plane"] == pytest.approx([-1.0, 0.0, 0.0, 0.0])
    assert "default" in side.settings["symmetry"] and side.settings["symmetry"].startswith("on")
    assert front.settings["symmetry_plane"] == pytest.approx([0.0, 1.0, 0.0, 0.0])
    assert off.settings["symmetry_plane"] is None and off.settings["symmetry"].startswith("off")
    assert not np.allclose(side.views, front.views) and not np.allclose(side.views, off.views)
    plain = Reconstructor.from_pretrained(plain_path)
    a = plain.reconstruct(tmp_path / "car.png", config=cfg)
    b = plain.reconstruct(tmp_path / "car.png", config=ReconstructConfig(views=2, mesh_resolution=0, facing=None))
    assert a.settings["symmetry_plane"] is None and "no mirror" in a.settings["symmetry"]
    np.testing.assert_array_equal(a.views, b.views)
    assert main(["reconstruct", str(tmp_path / "car.png"), "--checkpoint", str(mirror_path), "--out",
                 str(tmp_path / "out"), "--views", "2", "--mesh-resolution", "0", "--facing", "none",
                 "--no-progress"]) == 0
    assert "symmetry off: no facing given" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main(["reconstruct", str(tmp_path / "car.png"), "--checkpoint", str(mirror_path), "--out",
              str(tmp_path / "out2"), "--facing", "left"])
    assert "--facing: expected an angle in degrees, 'auto' or 'none'" in capsys.readouterr().err


def test_eval_records_the_plane_it_used(tmp_path):
    """eval conditions a mirror checkpoint on the dataset's plane (ShapeNet's without a card, the card's with one),
    on none with --no-symmetry, and says so in summary.json; a plain checkpoint records none."""
    from depthnerf.cli import main
    from depthnerf.config_io import apply_overrides
    from tests.fixtures_checkpoints import save_tiny, tiny_config
    from tests.fixtures_srn import make_srn_fixture

    root = make_srn_fixture(tmp_path / "data", "cars", splits={"test": 1}, views=3, size=16)
    plain_cfg = tiny_config("cars", "none")
    mirror = save_tiny(tmp_path / "mirror.safetensors", apply_overrides(plain_cfg, ["--model.mirror", "true"]))
    plain = save_tiny(tmp_path / "plain.safetensors", plain_cfg)

    def summary(ckpt, out, *flags):
        assert main(["eval", "--checkpoint", str(ckpt), "--data", str(root), "--out", str(tmp_path / out),
                     "--no-mesh", "--no-progress", *flags]) == 0
        return json.loads((tmp_path / out / "summary.json").read_text())

    shapenet = summary(mirror, "a")
    assert shapenet["symmetry_plane"] == [1.0, 0.0, 0.0, 0.0] and "ShapeNet" in shapenet["symmetry_plane_source"]
    off = summary(mirror, "b", "--no-symmetry")
    assert off["symmetry_plane"] is None and off["symmetry_plane_source"] == "off (--no-symmetry)"
    assert off["psnr"] != shapenet["psnr"]
    (root / "cars_card.json").write_text(json.dumps(SYNTH_CARD))
    card = summary(mirror, "c")
    assert card["symmetry_plane"] == [0.0, 1.0, 0.0, 0.0] and card["psnr"] != shapenet["psnr"]
    assert summary(plain, "d")["symmetry_plane"] is None


def test_app_passes_the_facing_and_says_which_plane(tmp_path):
    """The page's facing slider reaches the mirror model, its checkbox turns the plane off, and the details say so."""
    from depthnerf.app.logic import AppConfig, AppSession, RunRequest, examples
    from depthnerf.config_io import apply_overrides
    from tests.fixtures_checkpoints import save_tiny, tiny_config

    mirror = save_tiny(tmp_path / "mirror.safetensors",
                       apply_overrides(tiny_config("cars", "none"), ["--model.mirror", "true"]))
    session = AppSession(AppConfig(mesh_resolution=0, work_dir=tmp_path / "app", keep_runs=3))
    example = examples()[0]
    side = session.run(RunRequest(example, "car", checkpoint_path=str(mirror), views=1, facing=90.0))
    off = session.run(RunRequest(example, "car", checkpoint_path=str(mirror), views=1, facing=None))
    assert side.ok and off.ok, (side.message, off.message)
    assert "**Symmetry** on: the object faces 90 degrees (the default: a side view)" in side.details
    assert "**Symmetry** off: no facing given" in off.details
    auto = session.run(RunRequest(example, "car", checkpoint_path=str(mirror), views=1, facing="auto"))
    assert auto.ok and "--facing auto" in auto.details, auto.message
