"""``Reconstructor`` / ``depthnerf reconstruct``: photo preparation rules, outputs against closed forms, bad input.

One tiny depth-aware model (random ``bundled`` depth weights) is trained for one step through the real CLI;
derived checkpoints are written with the training checkpoint writer: a *constant field* (every ray renders the
constant colour at the first sample, every grid point has the constant density, so views, depths, points and the
mesh have closed forms), an ``oracle``-prior one and a baseline one.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import math
import re
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import safetensors.torch
import torch
import trimesh
from fixtures_checkpoints import save_tiny, tiny_config
from fixtures_srn import make_srn_fixture
from PIL import Image
from scipy import ndimage

from depthnerf.cli import main
from depthnerf.config_io import to_dict
from depthnerf.data.cameras import project, world_to_camera
from depthnerf.data.photo_framing import category_fill
from depthnerf.depth.bundled import BundledDepthNet, BundledNetConfig, save_bundled
from depthnerf.depth.normalize import BACKGROUND_VALUE
from depthnerf.errors import DepthnerfError
from depthnerf.model.pixelnerf import PixelNeRF
from depthnerf.pretrained.load import load_pretrained
from depthnerf.pretrained.spec import SPEC_KEY, spec_from_metadata
from depthnerf.pretrained.weights import read_weights
from depthnerf.reconstruct.orbit import srn_intrinsics
from depthnerf.reconstruct.photo import prepare_photo
from depthnerf.reconstruct.reconstructor import ReconstructConfig, Reconstructor
from depthnerf.render.config import DEFAULT_BUDGET
from depthnerf.render.mesh import CameraGrid
from depthnerf.render.source_guide import guided_config
from depthnerf.train import checkpoint as ckpt
from depthnerf.train.config import from_dict_config, with_prior

COLOR = (0.2, 0.6, 0.8)
TINY = ["--max-steps", "1", "--log.val_every", "0", "--data.resolution", "32", "--data.num_workers", "0",
        "--model.coarse.d_hidden", "32", "--model.fine.d_hidden", "32", "--model.encoder.backbone", "resnet18",
        "--schedule.objects_phase1", "1", "--schedule.rays_per_object", "32", "--render.sampler.n_coarse", "16",
        "--render.sampler.n_importance", "8", "--render.sampler.n_gaussian", "4", "--no-progress"]


def _save(dst: Path, model: PixelNeRF, cfg) -> Path:
    ckpt.save_weights(dst, model, to_dict(cfg.model), step=1, extra={"train_config": json.dumps(to_dict(cfg))})
    return dst


@pytest.fixture(scope="module")
def models(tmp_path_factory) -> dict[str, Path]:
    tmp = tmp_path_factory.mktemp("recon")
    root = make_srn_fixture(tmp / "data", "cars", {"train": 2}, views=4, size=32, with_mask=True)
    torch.manual_seed(0)
    weights = tmp / "bundled.safetensors"
    save_bundled(BundledDepthNet(BundledNetConfig(widths=(8, 8, 8), input_size=32, unshuffle=1)), weights)
    assert main(["depth", "--data", str(root), "--estimator", "bundled", "--checkpoint", str(weights),
                 "--splits", "train", "--no-progress"]) == 0
    assert main(["train", "--depth", "bundled", "--depth-checkpoint", str(weights), "--data", str(root),
                 "--out", str(tmp / "run"), *TINY]) == 0
    pre = load_pretrained(tmp / "run")
    logits = [math.log(c / (1 - c)) for c in COLOR]
    for net in (pre.model.coarse, pre.model.fine):
        net.lin_out.weight.data.zero_()
        net.lin_out.bias.data = torch.tensor([*logits, 1e4])
    run_cfg = from_dict_config(json.loads((tmp / "run" / "config.json").read_text()))
    base_cfg = with_prior(run_cfg, "none")
    return {"tmp": tmp, "weights": weights, "run": tmp / "run",
            "constant": _save(tmp / "constant.safetensors", pre.model, run_cfg),
            "oracle": _save(tmp / "oracle.safetensors", pre.model, with_prior(run_cfg, "oracle")),
            "baseline": _save(tmp / "baseline.safetensors", PixelNeRF(base_cfg.model, depth_aware=False), base_cfg)}


def disc_photo(h: int = 150, w: int = 200, center=(110, 70), radius: int = 40, bg=(40, 90, 160)) -> np.ndarray:
    img = np.empty((h, w, 3), np.uint8)
    img[:] = bg
    yy, xx = np.mgrid[:h, :w]
    img[(xx - center[0]) ** 2 + (yy - center[1]) ** 2 < radius**2] = (200, 50, 50)
    return img


def _bbox(mask: np.ndarray) -> tuple[int, int, int, int]:
    rows, cols = np.where(mask.any(1))[0], np.where(mask.any(0))[0]
    return cols[0], rows[0], cols[-1], rows[-1]


def test_framing_centres_the_object_at_the_training_fill():
    prep = prepare_photo(disc_photo(), None, 64, "auto", category_fill("cars"))
    x0, y0, x1, y1 = _bbox(prep.mask)
    side = max(x1 - x0 + 1, y1 - y0 + 1)
    assert abs(side / 64 - category_fill("cars")) <= 2 / 64  # mask = any coverage: at most a pixel wider on each side
    assert abs((x0 + x1) / 2 - 31.5) <= 1 and abs((y0 + y1) / 2 - 31.5) <= 1
    assert np.allclose(prep.image[~prep.mask], 1.0, atol=1e-6)  # the blue background became white
    assert np.allclose(prep.image[32, 32], np.array([200, 50, 50]) / 255, atol=1e-6)
    assert any("border colour [40, 90, 160]" in n for n in prep.notes)
    keep = prepare_photo(disc_photo(64, 64, (32, 32), 10), None, 32, "keep", 0.5)
    assert _bbox(keep.mask) == (11, 11, 20, 20)  # only resampled by 1/2: 20 px disc -> 10 px


@pytest.mark.parametrize(("box", "fill"), [((30, 50, 20, 60), 0.5), ((5, 25, 70, 95), 0.8), ((40, 60, 40, 60), 1.0)])
def test_framed_intrinsics_project_a_point_where_the_framed_image_shows_it(box, fill):
    """A point that projects to the centre of a dark block projects, with :func:`framed_intrinsics`, to the
    block's intensity centroid in the framed image (to a tenth of a framed pixel: area resampling moves it by
    less), also where the square reaches past the image (second case)."""
    from depthnerf.data.cameras import Intrinsics, project
    from depthnerf.data.photo_framing import frame_photo, framed_intrinsics, square_crop

    r0, r1, c0, c1 = box
    rgb = np.ones((100, 100, 3), np.float32)
    rgb[r0:r1, c0:c1] = 0.0
    mask = rgb[..., 0] < 0.5
    intr = Intrinsics(focal=120.0, cx=49.5, cy=49.5, height=100, width=100)
    u, v = (c0 + c1 - 1) / 2, (r0 + r1 - 1) / 2  # the block's centre in integer-centred pixel coordinates
    point = torch.tensor([[(u - intr.cx) / intr.focal * 2.0, (v - intr.cy) / intr.focal * 2.0, 2.0]])
    image, _ = frame_photo(rgb, None, mask, 32, "auto", fill, [])
    framed = framed_intrinsics(intr, square_crop(mask, "auto", fill), 32)
    expected = project(point, framed.focal, (framed.cx, framed.cy))[0].numpy()
    weight = 1.0 - image.mean(axis=2)
    rows, cols = np.mgrid[0:32, 0:32]
    centroid = np.array([(weight * cols).sum(), (weight * rows).sum()]) / weight.sum()
    np.testing.assert_allclose(centroid, expected, atol=0.1)
    assert framed.height == framed.width == 32


def test_mask_sources_alpha_given_grayscale():
    rgba = np.zeros((40, 40, 4), np.uint8)
    rgba[10:30, 5:25] = (0, 200, 0, 255)  # transparent black elsewhere: alpha decides, not colour
    prep = prepare_photo(Image.fromarray(rgba, "RGBA"), None, 32, "keep")
    assert "mask: alpha > 0.5" in prep.notes and _bbox(prep.mask) == (4, 8, 19, 23)
    assert np.allclose(prep.image[~prep.mask], 1.0, atol=1e-6)
    mask = np.zeros((40, 40), np.uint8)
    mask[0:8, 0:8] = 255
    given = prepare_photo(disc_photo(40, 40, (20, 20), 8), mask, 40, "keep")
    assert "mask: given (object: value > 127.5, half its maximum 255)" in given.notes and _bbox(given.mask) == (0, 0, 7, 7)
    grey = prepare_photo(Image.fromarray(disc_photo(40, 40, (20, 20), 8)[..., 0]), None, 40, "keep")
    assert "grayscale image: replicated to RGB" in grey.notes
    assert np.all(grey.image[..., 0] == grey.image[..., 2])


def test_bad_photos(tmp_path):
    (tmp_path / "junk.png").write_bytes(b"not an image")
    cases = [(tmp_path / "missing.png", "image file not found"), (tmp_path / "junk.png", "unreadable image"),
             (np.zeros((1, 1, 3), np.uint8), "image is 1x1 px; at least 16"),
             (np.zeros((15, 40, 3), np.uint8), "image is 40x15 px"),
             (np.full((40, 40, 3), 90, np.uint8), "no object found"),
             (np.zeros((4, 4, 5), np.uint8), "expected an H x W"),
             # arrays whose values were misread: "no object found", or a silently clipped or near-black photo
             (np.where(disc_photo() > 100, np.nan, 0.2), "image: the array holds NaN or inf"),
             (disc_photo().astype(np.float32), "image: a float array is read as values in [0, 1], got 40 to 200; "
                                               "divide 8-bit values by 255 or pass a uint8 array"),
             (disc_photo() / 255.0 - 0.5, "image: a float array is read as values in [0, 1], got -0.343137 to"),
             (disc_photo().astype(np.int64), "image: int64 pixels are read as 16-bit values (0-65535), got 40 to "
                                             "200; pass 8-bit values as a uint8 array"),
             (disc_photo().astype(object), "image: an array of object is not pixels")]
    for image, text in cases:
        with pytest.raises(DepthnerfError, match=re.escape(text)) as info:
            prepare_photo(image, None, 32)
        assert "\n" not in str(info.value)
    with pytest.raises(DepthnerfError, match="mask is 10x10 but the image is 40x40"):
        prepare_photo(disc_photo(40, 40, (20, 20), 8), np.ones((10, 10), np.uint8), 32)
    with pytest.raises(DepthnerfError, match="^image must be a file path, a PIL image or a numpy array, got int$"):
        prepare_photo(5, None, 32)
    # a photo given as the mask gets a note; a real (binary) mask does not
    photo = disc_photo(40, 40, (20, 20), 8)
    as_mask = np.linspace(0, 255, 40 * 40).reshape(40, 40).astype(np.uint8)
    noted = prepare_photo(photo, as_mask, 32).notes
    assert any("are neither dark nor bright (a photo rather than a mask?)" in n for n in noted), noted
    binary = np.zeros((40, 40), np.uint8)
    binary[10:30, 10:30] = 255
    assert not any("neither dark nor bright" in n for n in prepare_photo(photo, binary, 32).notes)
    # an empty mask is named as the mask's fault, a transparent cut-out as the alpha channel's
    with pytest.raises(DepthnerfError, match=r"^mask: the mask marks no object \(every pixel is 0\)$"):
        prepare_photo(disc_photo(40, 40, (20, 20), 8), np.zeros((40, 40), np.uint8), 32)
    clear = np.zeros((40, 40, 4), np.uint8)
    clear[..., :3] = 200
    with pytest.raises(DepthnerfError, match=r"no object found \(the alpha channel is transparent everywhere\)$"):
        prepare_photo(clear, None, 32)


def test_a_checkpoint_of_an_unknown_category_is_named_with_the_flags_that_replace_its_camera(tmp_path, capsys):
    """A spec naming a category without camera defaults (a hand-edited or foreign checkpoint): one line naming the
    checkpoint file and --radius / --focal, not the bare 'unknown SRN category' of the data reader."""
    path = save_tiny(tmp_path / "planes.safetensors", tiny_config("cars", "none"))
    tensors, meta = read_weights(path)
    spec = json.loads(spec_from_metadata(meta, str(path)).to_json())
    safetensors.torch.save_file(tensors, str(path), metadata={**meta, SPEC_KEY: json.dumps({**spec,
                                                                                          "category": "planes"})})
    Image.fromarray(disc_photo(64, 64, (32, 32), 16)).save(tmp_path / "photo.png")
    assert main(["reconstruct", "--checkpoint", str(path), str(tmp_path / "photo.png"), "--out",
                 str(tmp_path / "out"), "--background-removal", "off", "--views", "1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"error: {path}: unknown SRN category 'planes'"), err
    assert "pass both --radius and --focal" in err


def test_huge_image_is_downscaled_first():
    im = Image.new("RGB", (8000, 8000), (255, 255, 255))
    im.paste((10, 10, 10), (3000, 3500, 5000, 4500))
    prep = prepare_photo(im, None, 32, "auto", 0.5)
    assert "downscaled from 8000x8000 to 1024x1024 (box filter) first" in prep.notes
    x0, y0, x1, y1 = _bbox(prep.mask)
    assert abs((x1 - x0 + 1) - 16) <= 2 and abs((y1 - y0 + 1) - 8) <= 2  # 2:1 box, longer side = half the frame


def test_a_small_fill_frames_in_bounded_memory_as_the_full_square_would(monkeypatch):
    """A small fill asks for a square far wider than the photo (8000 px for a 400 px object at 0.05, 770 MB at the
    photo's scale): it is framed at a reduced scale, in bounded memory, and gives what the full square gives."""
    import tracemalloc

    from depthnerf.data import photo_framing

    disc = disc_photo(600, 600, (300, 300), 200)
    tracemalloc.start()
    try:
        tiny = prepare_photo(disc, None, 64, "auto", 0.05)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 300e6, peak
    x0, y0, x1, y1 = _bbox(tiny.mask)
    assert 3 <= max(x1 - x0 + 1, y1 - y0 + 1) <= 5 and abs((x0 + x1) / 2 - 31.5) <= 1 and abs((y0 + y1) / 2 - 31.5) <= 1
    reduced = prepare_photo(disc, None, 64, "auto", 0.075)  # a 5334 px square: just above MAX_CANVAS
    monkeypatch.setattr(photo_framing, "MAX_CANVAS", 10**6)
    full = prepare_photo(disc, None, 64, "auto", 0.075)
    assert np.abs(reduced.image - full.image).max() < 0.02 and (reduced.mask == full.mask).all()


def test_constant_field_reconstruction_matches_closed_forms(models):
    rec = Reconstructor.from_pretrained(models["constant"])
    cfg = ReconstructConfig(views=4, elevation=30.0, mesh_resolution=10, mesh_keep="largest")
    res = rec.reconstruct(disc_photo(), config=cfg)
    assert res.settings["mesh_pieces"] == 1 and res.settings["mesh_faces_kept"] == len(res.mesh.faces) > 0
    assert np.abs(res.views - np.array(COLOR)).max() < 1e-4 and res.opacity.min() > 1 - 1e-4
    assert res.depths.min() >= 0.8 and res.depths.max() <= 0.8 + 1.0 / 16  # first coarse bin of [0.8, 1.8]
    eyes = res.poses[:, :3, 3]
    assert np.allclose(np.linalg.norm(eyes, axis=1), 1.3, atol=1e-5)  # cars radius
    assert np.allclose(eyes[:, 2], 1.3 * math.sin(math.radians(30)), atol=1e-5)
    assert np.allclose(eyes[0], [1.3 * math.cos(math.radians(30)), 0, 1.3 * math.sin(math.radians(30))], atol=1e-5)
    assert np.allclose(np.arctan2(eyes[:, 1], eyes[:, 0]), np.radians([0, 90, 180, -90]), atol=1e-5)
    assert len(res.points) == 4 * 32 * 32  # every pixel is opaque; points are view-major
    dist = np.linalg.norm(res.points.reshape(4, -1, 3) - eyes[:, None], axis=-1)
    assert np.all((dist >= 0.8 - 1e-4) & (dist <= 0.8 + 1.0 / 16 + 1e-4))
    assert np.allclose(res.point_colors, COLOR, atol=1e-4)
    # photo colours without a fill: the photo's red disc where the input camera sees the mesh well inside it, the
    # field's colour wherever the vertex projects off the object; with the default fill the red spreads into those
    unfilled = rec.reconstruct(disc_photo(), config=dataclasses.replace(cfg, mesh_fill=0.0, views=1))
    assert np.array_equal(unfilled.mesh.vertices, res.mesh.vertices)
    rgb = unfilled.mesh.visual.vertex_colors[:, :3].astype(int)
    cam = world_to_camera(torch.as_tensor(res.mesh.vertices), torch.from_numpy(res.poses[0]).double())
    uv = np.rint(project(cam, res.intrinsics.focal, (res.intrinsics.cx, res.intrinsics.cy)).numpy()).astype(int)
    uv = np.clip(uv, 0, np.array(res.input.mask.shape[::-1]) - 1)
    inside = ndimage.distance_transform_edt(res.input.mask)[uv[:, 1], uv[:, 0]]  # pixels to the mask's edge
    to_eye = res.poses[0][:3, 3] - np.asarray(res.mesh.vertices)
    cos = (np.asarray(res.mesh.vertex_normals) * to_eye).sum(1) / np.linalg.norm(to_eye, axis=1)
    facing = cos > 0.5
    assert (inside >= 3).sum() > 10 and (inside == 0).sum() > 10
    assert np.abs(rgb[(inside >= 3) & facing] - [200, 50, 50]).max() <= 1
    assert np.all(rgb[inside == 0] == np.round(np.array(COLOR) * 255))
    filled = res.mesh.visual.vertex_colors[:, :3].astype(int)
    assert np.abs(filled[(inside >= 3) & facing] - [200, 50, 50]).max() <= 1
    red_share = (filled[inside == 0, 0] - 255 * COLOR[0]) / (200 - 255 * COLOR[0])  # 0: the field's, 1: the disc's
    assert 0 < red_share.mean() < 1 and red_share.min() >= 0
    field = rec.reconstruct(disc_photo(), config=dataclasses.replace(cfg, mesh_colors="normal-ray", views=1))
    assert np.all(field.mesh.visual.vertex_colors[:, :3] == np.round(np.array(COLOR) * 255))
    grid = CameraGrid.from_frustum(torch.from_numpy(res.poses[0]), srn_intrinsics(131.25, 128, 32), 0.8, 1.8)
    cam = world_to_camera(torch.as_tensor(res.mesh.vertices, dtype=torch.float32), torch.from_numpy(res.poses[0]))
    step = grid.layout(10)[1]
    assert np.all(cam.min(0).values.numpy() <= np.array(grid.lo) + 1e-4)
    assert np.all(cam.max(0).values.numpy() <= np.array(grid.hi) + 2 * step)
    assert res.prior_normalized is not None and res.depth_prior is not None
    assert np.all(res.prior_normalized[~res.input.mask] == BACKGROUND_VALUE)
    assert res.settings["depth_estimator"] == "bundled" and res.settings["fill"] == category_fill("cars", res.settings["training_framing"])


@pytest.mark.parametrize("rule", ["photo", "normal-ray", "point"])
def test_the_manifests_mesh_note_names_the_colour_rule(models, tmp_path, rule):
    """The note said "vertex colours from the fine network" whatever the rule, the photo's colours included."""
    rec = Reconstructor.from_pretrained(models["constant"])
    res = rec.reconstruct(disc_photo(), config=ReconstructConfig(views=1, mesh_resolution=8, mesh_colors=rule))
    manifest = rec.save(res, tmp_path / rule)
    assert manifest["mesh"]["faces"] > 0
    assert manifest["mesh"]["note"] == f"world frame, vertex colours by the {rule} rule (settings: mesh_colors)"


def test_cli_writes_every_listed_output(models, tmp_path, capsys):
    photo, mask = tmp_path / "photo.png", tmp_path / "mask.png"
    Image.fromarray(disc_photo()).save(photo)
    Image.fromarray((disc_photo()[..., 0] == 200).astype(np.uint8) * 255).save(mask)
    out = tmp_path / "out"
    assert main(["reconstruct", str(photo), "--checkpoint", str(models["run"]), "--out", str(out), "--views", "3",
                 "--mask", str(mask), "--mesh-resolution", "8", "--mesh-keep", "largest", "--mesh-colors", "point",
                 "--no-progress"]) == 0
    assert "wrote 3 views" in capsys.readouterr().out
    manifest = json.loads((out / "manifest.json").read_text())
    files = manifest["files"]
    listed = [v for k, v in files.items() if isinstance(v, str)] + files["views"] + files["depths"]
    assert all((out / p).is_file() for p in listed) and files["depth_prior"] == "depth_prior.png"
    assert iio.imread(out / files["turntable_gif"]).shape == (3, 32, 32, 3)
    if files["turntable_mp4"] is None:
        assert "imageio-ffmpeg is not installed" in manifest["turntable_mp4_status"]
    header = (out / "points.ply").read_bytes().split(b"end_header")[0].decode()
    assert f"element vertex {manifest['point_cloud']['points']}\n" in header and "property uchar red" in header
    ply, glb = trimesh.load(out / "mesh.ply", force="mesh"), trimesh.load(out / "mesh.glb", force="mesh")
    x, y, z = np.asarray(ply.vertices, np.float64).T  # glTF is +y up: (x, y, z) -> (x, z, -y)
    assert np.allclose(np.sort(np.asarray(glb.vertices), 0), np.sort(np.stack([x, z, -y], 1), 0), atol=1e-5)
    with np.load(out / "depths.npz", allow_pickle=False) as d:
        assert d["depth"].shape == (3, 32, 32) and d["poses"].shape == (3, 4, 4)
    assert manifest["checkpoint_sha256"] and manifest["settings"]["views"] == 3
    settings = manifest["settings"]
    assert settings["mesh_keep"] == "largest" and "seen along the input camera's ray" in settings["mesh_colors"]
    assert len(ply.faces) == settings["mesh_faces_kept"] <= settings["mesh_faces_extracted"]
    assert "mask: given (object: value > 127.5, half its maximum 255)" in manifest["input"]["notes"]


def test_baseline_has_no_prior_and_other_resolution(models, tmp_path, monkeypatch):
    rec = Reconstructor.from_pretrained(models["baseline"])
    res = rec.reconstruct(disc_photo(), views=2, config=ReconstructConfig(mesh_resolution=0, render_resolution=16))
    assert res.depth_prior is None and res.views.shape == (2, 16, 16, 3) and len(res.mesh.faces) == 0
    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "imageio_ffmpeg"
                        else find_spec(name, *a))
    manifest = rec.save(res, tmp_path / "b")
    assert manifest["files"]["depth_prior"] is None and manifest["mesh"]["empty"]
    assert manifest["files"]["turntable_mp4"] is None and not (tmp_path / "b" / "turntable.mp4").exists()
    assert "imageio-ffmpeg is not installed" in manifest["turntable_mp4_status"]


def test_an_odd_render_size_still_writes_the_mp4(models, tmp_path):
    """libx264 needs even sides: at 17 px ffmpeg wrote an empty turntable.mp4 that the manifest called "ok"."""
    pytest.importorskip("imageio_ffmpeg")
    rec = Reconstructor.from_pretrained(models["baseline"])
    res = rec.reconstruct(disc_photo(), views=2, config=ReconstructConfig(mesh_resolution=0, render_resolution=17))
    manifest = rec.save(res, tmp_path / "odd")
    assert manifest["turntable_mp4_status"] == "ok"
    frames = iio.imread(tmp_path / "odd" / "turntable.mp4", plugin="FFMPEG")
    assert frames.shape[1:3] == (18, 18)  # one edge-copied row and column; the GIF and views keep 17
    assert iio.imread(tmp_path / "odd" / "turntable.gif").shape == (2, 17, 17, 3)


def test_even_sized_copies_the_last_row_and_column():
    from depthnerf.reconstruct.exports import even_sized

    frames = np.arange(2 * 3 * 5 * 3, dtype=np.uint8).reshape(2, 3, 5, 3)
    grown = even_sized(frames)
    assert grown.shape == (2, 4, 6, 3) and np.array_equal(grown[:, :3, :5], frames)
    assert np.array_equal(grown[:, 3, :5], frames[:, 2]) and np.array_equal(grown[:, :3, 5], frames[:, :, 4])
    assert even_sized(grown) is grown


def test_bad_checkpoints(models, tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("hello")
    photo = tmp_path / "photo.png"  # a real photo: a missing one is refused before the checkpoint loads
    Image.fromarray(disc_photo()).save(photo)
    cases = [(tmp_path / "notes.txt", "not a readable safetensors checkpoint"),
             (models["weights"], "not a depthnerf checkpoint"),
             (models["oracle"], "which a photo does not have; pass --depth ")]
    for path, text in cases:
        assert main(["reconstruct", str(photo), "--checkpoint", str(path), "--out", str(tmp_path / "o")]) == 2
        err = capsys.readouterr().err
        assert text in err and err.count("\n") == 1
    rec = Reconstructor.from_pretrained(models["oracle"], depth_estimator="bundled",
                                        depth_checkpoint=str(models["weights"]))
    assert rec.session.prior_source.kind == "live" and rec.session.prior_source.estimator.name == "bundled"


def test_out_of_memory_while_reconstructing_is_one_line_naming_the_sizes(models, tmp_path, capsys, monkeypatch):
    """``--render-resolution 100000`` made the CPU allocator fail in a traceback; it is one line naming the flags
    that size the work, exit 2, and no output folder."""
    photo = tmp_path / "photo.png"
    Image.fromarray(disc_photo()).save(photo)

    def fail(*args, **kwargs):
        raise RuntimeError("[enforce fail at alloc_cpu.cpp:127] err == 0. DefaultCPUAllocator: can't allocate "
                           "memory: you tried to allocate 40000000000 bytes. Error code 12")

    monkeypatch.setattr(Reconstructor, "reconstruct", fail)
    out = tmp_path / "o"
    assert main(["reconstruct", str(photo), "--checkpoint", str(models["baseline"]), "--out", str(out),
                 "--views", "3", "--render-resolution", "100000", "--mesh-resolution", "0", "--device", "cpu"]) == 2
    err = capsys.readouterr().err
    assert err == (f"error: out of memory on cpu (could not allocate 37.3 GiB) reconstructing {photo}: 3 views at "
                   "--render-resolution 100000, --chunk 4096 rays per pass, --mesh-resolution 0; lower them\n")
    assert not out.exists()


def test_guided_reconstruction_from_the_api_and_the_cli(models, tmp_path, capsys):
    rec = Reconstructor.from_pretrained(models["constant"])
    cfg = ReconstructConfig(views=2, mesh_resolution=0, guided=guided_config(12))
    res = rec.reconstruct(disc_photo(), config=cfg)
    assert np.abs(res.views - np.array(COLOR)).max() < 1e-4 and res.opacity.min() > 1 - 1e-4
    assert res.settings["guided_sampling"] == 12
    plain = rec.reconstruct(disc_photo(), config=ReconstructConfig(views=2, mesh_resolution=0))
    assert plain.settings["guided_sampling"] is None and np.allclose(plain.views, res.views, atol=1e-4)
    (tmp_path / "photo.png").write_bytes(b"")
    Image.fromarray(disc_photo()).save(tmp_path / "photo.png")
    assert main(["reconstruct", str(tmp_path / "photo.png"), "--checkpoint", str(models["constant"]), "--out",
                 str(tmp_path / "g"), "--views", "2", "--mesh-resolution", "0", "--guided", "--no-progress",
                 "--depth-estimator", "bundled", "--depth-checkpoint", str(models["weights"])]) == 0
    manifest = json.loads((tmp_path / "g" / "manifest.json").read_text())
    assert manifest["settings"]["guided_sampling"] == DEFAULT_BUDGET == 48
    assert manifest["settings"]["depth_estimator"] == "bundled"
    assert main(["reconstruct", str(tmp_path / "photo.png"), "--checkpoint", str(models["constant"]), "--out",
                 str(tmp_path / "h"), "--guided", "5"]) == 2
    assert "--guided 5: a guided budget needs >= 6" in capsys.readouterr().err



def test_samples_flag_sets_the_sampler_counts_of_a_reconstruction(models, tmp_path, capsys):
    """``reconstruct --samples C I G`` renders with those counts and records them in manifest.json; counts the
    sampler cannot take are refused before the model loads."""
    photo = tmp_path / "photo.png"
    Image.fromarray(disc_photo()).save(photo)
    counts = {}
    for name, flags in (("own", []), ("few", ["--samples", "4", "2", "0"])):
        assert main(["reconstruct", str(photo), "--checkpoint", str(models["baseline"]), "--out", str(tmp_path / name),
                     "--views", "2", "--mesh-resolution", "0", "--no-progress", *flags]) == 0
        counts[name] = json.loads((tmp_path / name / "manifest.json").read_text())["settings"]["sampler_counts"]
    own = Reconstructor.from_pretrained(models["baseline"]).session.spec.render.sampler
    assert counts == {"own": [own.n_coarse, own.n_importance, own.n_gaussian], "few": [4, 2, 0]}
    capsys.readouterr()
    assert main(["reconstruct", str(photo), "--checkpoint", str(tmp_path / "missing.safetensors"), "--out",
                 str(tmp_path / "bad"), "--samples", "1", "2", "3"]) == 2
    assert "--samples takes three counts, coarse >= 2" in capsys.readouterr().err


def test_the_python_api_takes_a_guided_budget_as_the_cli_does(models):
    """``guided=12`` (session or per call) is ``--guided 12``; ``True`` the default budget; other values one line."""
    rec = Reconstructor.from_pretrained(models["constant"], guided=12)
    assert rec.session.guided == dataclasses.replace(guided_config(12), enabled=True)
    assert Reconstructor.from_pretrained(models["constant"], guided=True).session.guided.budget == DEFAULT_BUDGET
    assert Reconstructor.from_pretrained(models["constant"], guided=False).session.guided is None
    res = rec.reconstruct(disc_photo(), config=ReconstructConfig(views=2, mesh_resolution=0))
    assert res.settings["guided_sampling"] == 12
    plain = rec.reconstruct(disc_photo(), config=ReconstructConfig(views=2, mesh_resolution=0, guided=False))
    assert plain.settings["guided_sampling"] is None
    per_call = Reconstructor.from_pretrained(models["constant"]).reconstruct(
        disc_photo(), config=ReconstructConfig(views=2, mesh_resolution=0, guided=24))
    assert per_call.settings["guided_sampling"] == 24
    with pytest.raises(DepthnerfError) as err:
        Reconstructor.from_pretrained(models["constant"], guided="fast")
    assert str(err.value).startswith("guided='fast': give a budget") and "\n" not in str(err.value)

def test_config_names_the_flag_of_a_setting_that_cannot_work():
    for kwargs, message in (({"mesh_keep": "most"}, "--mesh-keep must be one of all, largest, got 'most'"),
                            ({"framing": "tight"}, "--framing must be 'auto' or 'keep', got 'tight'"),
                            ({"fill": 1.5}, "--fill must be in (0, 1], got 1.5"),
                            ({"views": 2.5}, "--views must be a whole number, got 2.5"),  # was a TypeError
                            ({"render_resolution": 16.5}, "--render-resolution must be a whole number, got 16.5"),
                            ({"mesh_resolution": 8.5}, "--mesh-resolution must be a whole number, got 8.5"),
                            # a level <= 0 or NaN was used as given: every grid cell inside, or an empty mesh
                            ({"mesh_threshold": -1.0}, "--mesh-threshold: must be a positive number or one of "
                                                       "auto, silhouette, local, got '-1.0'"),
                            ({"mesh_threshold": float("nan")}, "--mesh-threshold: must be a positive number or one "
                                                               "of auto, silhouette, local, got 'nan'")):
        with pytest.raises(DepthnerfError) as err:
            ReconstructConfig(**kwargs)
        assert str(err.value) == message
