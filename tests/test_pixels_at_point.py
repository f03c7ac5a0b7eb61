"""The source pixels read at each point (``PixelNeRFConfig.prior_at_point`` / ``rgb_at_point``) and the mirror
branch (``PixelNeRFConfig.mirror``): the field against a brute-force loop (points and mirror images projected by
hand, the prior and colour read bilinearly by hand), the default model unchanged, the columns train, and a model
without a prior refuses ``prior_at_point``."""

from __future__ import annotations

import pytest
import torch

from depthnerf.data.cameras import project, world_to_camera
from depthnerf.errors import DepthnerfError
from depthnerf.model import PixelNeRF
from depthnerf.model.config import PRIOR_POINT_SCALE
from tests.test_model import bilinear_border, query, randomize, small_config, sources


def reference_field(model: PixelNeRF, enc, src, which: str, pts, dirs):
    """Point by point (one source view): pixelNeRF's field, the source pixels (prior, then colour) at the point's
    projection appended to its input, for mirror models the mirror branch (the mirror image projected by
    hand, its flags, and those pixels at its projection), and for global-feature models the feature maps' mean
    through ``lin_global``."""
    mlp = model.network(which)
    h, w = enc.image_size
    hf, wf = enc.features.shape[-2:]
    plane = src.symmetry_plane
    rgb, sigma = torch.zeros(*pts.shape), torch.zeros(pts.shape[:-1])
    for bi in range(pts.shape[0]):
        c2w = src.poses[bi, 0]
        rot = c2w[:3, :3].T
        pixels = []  # [K H W]: what the model reads at a projection
        if model.cfg.prior_at_point:
            pixels.append(src.disparity[bi, 0] * PRIOR_POINT_SCALE)
        if model.cfg.rgb_at_point:
            pixels.append(src.images[bi, 0] * 2 - 1)
        pixels = torch.cat(pixels) if pixels else src.images.new_zeros(0, h, w)
        for ri in range(pts.shape[1]):
            for si in range(pts.shape[2]):
                p, v = pts[bi, ri, si], dirs[bi, ri]
                queries = [(p, v)]
                if model.cfg.mirror:
                    n, d = plane[bi, :3], plane[bi, 3]
                    queries.append((p - 2 * (p @ n - d) * n, v - 2 * (v @ n) * n))
                feats, flags, pixel_cols = [], [], []
                for q, _ in queries:
                    cam = world_to_camera(q[None], c2w)[0]
                    u, vv = project(cam[None], float(src.focal[bi]), tuple(src.principal[bi].tolist()))[0]
                    feats.append(bilinear_border(enc.features[bi, 0], float(u) * wf / w, float(vv) * hf / h))
                    flags.append(float(cam[2] > 0 and 0 <= u <= w and 0 <= vv <= h))
                    pixel_cols.append(bilinear_border(pixels, float(u), float(vv)))
                x = mlp.lin_in(torch.cat([mlp.encoding(rot @ p), rot @ v, pixel_cols[0]]))
                if model.cfg.global_features:
                    x = x + mlp.lin_global(enc.features[bi, 0].mean(dim=(1, 2)))
                gate = 0.0
                if model.cfg.mirror:
                    gate = float(plane[bi, :3].abs().sum() > 0)
                    pm, vm = queries[1]
                    x = x + gate * mlp.lin_in_mirror(torch.cat([mlp.encoding(rot @ pm), rot @ vm,
                                                                torch.tensor(flags), pixel_cols[1]]))
                for k in range(mlp.cfg.combine_layer):
                    x = x + mlp.lin_z[k](feats[0])
                    if model.cfg.mirror:
                        x = x + gate * mlp.lin_z_mirror[k](feats[1])
                    blk = mlp.blocks[k]
                    x = x + blk.fc_1(torch.relu(blk.fc_0(torch.relu(x))))
                for blk in mlp.blocks[mlp.cfg.combine_layer:]:
                    x = x + blk.fc_1(torch.relu(blk.fc_0(torch.relu(x))))
                out = mlp.lin_out(torch.relu(x))
                rgb[bi, ri, si], sigma[bi, ri, si] = torch.sigmoid(out[:3]), torch.relu(out[3])
    return rgb, sigma


def prior_model(mirror: bool, on_map: bool = True, prior: bool = True, rgb: bool = False,
                depth_aware: bool = True) -> PixelNeRF:
    cfg = small_config(lin_z_on_map=on_map)
    cfg.mirror, cfg.prior_at_point, cfg.rgb_at_point = mirror, prior, rgb
    return randomize(PixelNeRF(cfg, depth_aware=depth_aware))


@pytest.mark.parametrize(("mirror", "on_map", "prior", "rgb", "depth_aware"),
                         [(True, True, False, False, False), (True, False, False, False, False),  # mirror alone
                          (False, True, True, False, True), (True, True, True, False, True),
                          (True, False, True, False, True), (False, True, False, True, True),
                          (True, True, True, True, True)])
def test_field_matches_bruteforce_reference(mirror, on_map, prior, rgb, depth_aware):
    torch.manual_seed(0)
    check_against_reference(prior_model(mirror, on_map, prior, rgb, depth_aware))


def check_against_reference(model: PixelNeRF) -> None:
    """Both passes of ``model``'s field on three one-view objects (planes for mirror models: two objects with one,
    one without; a point projecting outside the image) equal :func:`reference_field`, with a live density."""
    mirror = model.cfg.mirror
    src = sources(b=3, v=1, size=40, prior=True)
    src.disparity = src.disparity * 9.0 - 5.0  # the normalised prior's range: [-5, 4]
    if mirror:
        src.symmetry_plane = torch.tensor([[0.0, 1.0, 0.0, 0.0], [0.6, 0.0, 0.8, 0.1], [0.0, 0.0, 0.0, 0.0]])
    pts, dirs = query(b=3, r=3, s=4)
    pts[1, 0, 0] = torch.tensor([0.4, 0.0, -3.0])  # projects (and its mirror image) outside the image: border
    with torch.no_grad():
        enc = model.encode(src)
        for which in ("coarse", "fine"):
            rgb, sigma = model.field(enc, which)(pts, dirs)
            ref_rgb, ref_sigma = reference_field(model, enc, src, which, pts, dirs)
            torch.testing.assert_close(rgb, ref_rgb, atol=1e-5, rtol=1e-4)
            torch.testing.assert_close(sigma, ref_sigma, atol=1e-5, rtol=1e-4)
    assert (sigma > 0).any() and rgb.std() > 1e-3


def test_the_prior_column_reads_the_prior_and_trains():
    """Changing the prior changes the field only through the new column; its weights get a gradient."""
    torch.manual_seed(0)
    model = prior_model(mirror=True)
    src = sources(b=2, v=1, size=32, prior=True)
    src.symmetry_plane = torch.tensor([[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]])
    pts, dirs = query(b=2)
    with torch.no_grad():
        enc = model.encode(src)
        before = model.field(enc, "fine")(pts, dirs)
        enc.point_map = enc.point_map + 0.5  # the same features, another prior at every point
        after = model.field(enc, "fine")(pts, dirs)
    assert (after[1] - before[1]).abs().max() > 1e-4
    model.train()
    rgb, sigma = model.field(model.encode(src), "coarse")(pts, dirs)
    (rgb.sum() + sigma.sum()).backward()
    assert model.coarse.lin_in.weight.grad[:, -1].abs().sum() > 0
    assert model.coarse.lin_in_mirror.weight.grad[:, -1].abs().sum() > 0


def test_off_by_default_and_refused_without_a_prior():
    plain = PixelNeRF(small_config(), depth_aware=True)
    assert plain.coarse.lin_in.in_features == plain.cfg.coarse.d_in  # checkpoints without the option load as-is
    assert plain.encode(sources(b=1, prior=True)).point_map is None
    both = prior_model(mirror=True, rgb=True)
    assert both.coarse.lin_in.in_features == both.cfg.coarse.d_in + 4
    assert both.fine.lin_in_mirror.in_features == both.cfg.fine.d_in + 2 + 4
    with pytest.raises(DepthnerfError, match="prior_at_point reads the depth prior"):
        cfg = small_config()
        cfg.prior_at_point = True
        PixelNeRF(cfg, depth_aware=False)


def test_checkpoint_with_both_options_evaluates_and_reconstructs(tmp_path):
    """A mirror checkpoint reading the prior and colour at each point loads from its weights alone, is evaluated
    (the summary's method names both options, and the encoder's input scale) and reconstructs a photo."""
    import json

    from PIL import Image

    from depthnerf.cli import main
    from depthnerf.config_io import apply_overrides
    from tests.fixtures_checkpoints import save_tiny, tiny_bundled, tiny_config
    from tests.fixtures_srn import make_srn_fixture

    root = make_srn_fixture(tmp_path / "data", "cars", splits={"test": 1}, views=3, size=16)
    weights = tiny_bundled(tmp_path / "depth.safetensors")
    cfg = apply_overrides(tiny_config("cars", "bundled", weights), [
        "--model.mirror", "true", "--model.prior_at_point", "true", "--model.rgb_at_point", "true",
        "--model.encoder.image_scale", "2"])
    ckpt = save_tiny(tmp_path / "both.safetensors", cfg)
    assert main(["depth", "--data", str(root), "--depth", "bundled", "--depth-checkpoint", str(weights),
                 "--resolution", "16", "--no-progress"]) == 0
    assert main(["eval", "--checkpoint", str(ckpt), "--data", str(root), "--out", str(tmp_path / "ev"),
                 "--no-mesh", "--no-progress"]) == 0
    summary = json.loads((tmp_path / "ev" / "summary.json").read_text())
    assert summary["method"].endswith("+ mirror symmetry + prior at each point + colour at each point"
                                      " + encoder at 2x input")
    assert 5 < summary["psnr"] < 60
    photo = next((root / "cars_test").glob("*/rgb/*.png"))
    Image.open(photo).save(tmp_path / "car.png")
    assert main(["reconstruct", str(tmp_path / "car.png"), "--checkpoint", str(ckpt), "--out",
                 str(tmp_path / "rec"), "--views", "2", "--mesh-resolution", "0"]) == 0
    assert (tmp_path / "rec" / "manifest.json").is_file()
