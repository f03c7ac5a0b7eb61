"""Global features (``PixelNeRFConfig.global_features``): the field against brute-force loops (one view with the
mirror branch and the pixels at the point; two views, each with its own maps' mean, averaged at the combine
layer), off by default, the new weights and the encoder train through it, and a warm start from a model without
them starts at exactly that model's function."""

from __future__ import annotations

import pytest
import torch

from depthnerf.data.cameras import project, world_to_camera
from depthnerf.errors import DepthnerfError
from depthnerf.model import PixelNeRF
from tests.test_model import bilinear_border, query, randomize, small_config, sources
from tests.test_pixels_at_point import check_against_reference


def global_model(mirror: bool = False, on_map: bool = True, prior: bool = False, depth_aware: bool = True,
                 seed: int = 0) -> PixelNeRF:
    cfg = small_config(lin_z_on_map=on_map)
    cfg.mirror, cfg.prior_at_point, cfg.global_features = mirror, prior, True
    model = randomize(PixelNeRF(cfg, depth_aware=depth_aware), seed)
    with torch.no_grad():
        for mlp in (model.coarse, model.fine):
            mlp.lin_out.bias[3] += 10.0  # a live density at most points, so the comparison covers it
    return model


def multiview_reference(model: PixelNeRF, enc, src, which: str, pts, dirs):
    """Point by point over V views (no mirror, no pixels at the point): per view ``lin_in(u) + lin_global(mean of
    that view's maps)``, the features added before each block below the combine layer, the views averaged there."""
    mlp = model.network(which)
    h, w = enc.image_size
    hf, wf = enc.features.shape[-2:]
    n_views = src.poses.shape[1]
    rgb, sigma = torch.zeros(*pts.shape), torch.zeros(pts.shape[:-1])
    for bi in range(pts.shape[0]):
        for ri in range(pts.shape[1]):
            for si in range(pts.shape[2]):
                p, d = pts[bi, ri, si], dirs[bi, ri]
                per_view = []
                for vi in range(n_views):
                    c2w = src.poses[bi, vi]
                    rot = c2w[:3, :3].T
                    cam = world_to_camera(p[None], c2w)[0]
                    u, v = project(cam[None], float(src.focal[bi]), tuple(src.principal[bi].tolist()))[0]
                    feat = bilinear_border(enc.features[bi, vi], float(u) * wf / w, float(v) * hf / h)
                    x = mlp.lin_in(torch.cat([mlp.encoding(rot @ p), rot @ d]))
                    x = x + mlp.lin_global(enc.features[bi, vi].mean(dim=(1, 2)))
                    for k in range(mlp.cfg.combine_layer):
                        x = x + mlp.lin_z[k](feat)
                        blk = mlp.blocks[k]
                        x = x + blk.fc_1(torch.relu(blk.fc_0(torch.relu(x))))
                    per_view.append(x)
                x = torch.stack(per_view).mean(dim=0)
                for blk in mlp.blocks[mlp.cfg.combine_layer:]:
                    x = x + blk.fc_1(torch.relu(blk.fc_0(torch.relu(x))))
                out = mlp.lin_out(torch.relu(x))
                rgb[bi, ri, si], sigma[bi, ri, si] = torch.sigmoid(out[:3]), torch.relu(out[3])
    return rgb, sigma


@pytest.mark.parametrize(("mirror", "on_map", "prior", "depth_aware"),
                         [(False, True, False, False), (True, True, True, True), (True, False, False, True)])
def test_one_view_field_matches_the_bruteforce_reference(mirror, on_map, prior, depth_aware):
    torch.manual_seed(0)
    check_against_reference(global_model(mirror, on_map, prior, depth_aware))


@pytest.mark.parametrize("on_map", [True, False])
def test_two_view_field_matches_the_bruteforce_reference(on_map):
    model = global_model(on_map=on_map, depth_aware=False, seed=3)
    src = sources(b=2, v=2, size=24, seed=4)
    pts, dirs = query(b=2, r=2, s=3, seed=5)
    with torch.no_grad():
        enc = model.encode(src)
        rgb, sigma = model.field(enc, "fine")(pts, dirs)
        ref_rgb, ref_sigma = multiview_reference(model, enc, src, "fine", pts, dirs)
    torch.testing.assert_close(rgb, ref_rgb, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(sigma, ref_sigma, atol=1e-5, rtol=1e-4)


def test_the_term_is_each_views_own_mean_and_off_by_default():
    """Replacing one object's maps by maps with the same mean changes nothing of the global term; the plain model
    has no ``lin_global`` (checkpoints without the option load as they are) and refuses a term."""
    model = global_model(depth_aware=False)
    feats = torch.randn(2, 1, model.cfg.encoder.latent_size(False), 5, 5)
    shuffled = feats.flatten(-2)[..., torch.randperm(25)].reshape(feats.shape)
    torch.testing.assert_close(model.coarse.global_term(feats), model.coarse.global_term(shuffled))
    assert model.coarse.global_term(feats).shape == (2, 1, model.cfg.coarse.d_hidden)
    plain = PixelNeRF(small_config(), depth_aware=False)
    assert not any("lin_global" in k for k in plain.state_dict())
    with pytest.raises(ValueError, match="without lin_global"):
        plain.coarse.global_term(feats)


def test_the_new_linear_and_the_encoder_train_through_it():
    model = global_model(depth_aware=True).train()
    src = sources(b=2, v=1, size=32, prior=True)
    pts, dirs = query(b=2)
    rgb, sigma = model.field(model.encode(src), "coarse")(pts, dirs)
    (rgb.sum() + sigma.sum()).backward()
    assert model.coarse.lin_global.weight.grad.abs().sum() > 0
    assert model.fine.lin_global.weight.grad is None  # the fine network is not in this pass
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.encoder.parameters())


def test_warm_start_from_a_model_without_them_starts_at_its_function(tmp_path):
    """``--init-from`` a checkpoint without global features into a run with them: every source tensor loads, the
    new linears start at zero, the run's field equals the source's, and the new weights get a gradient. The other
    way round (dropping them) is refused like any other model difference."""
    from depthnerf.config_io import apply_overrides
    from depthnerf.train.warm_start import warm_start
    from tests.fixtures_checkpoints import save_tiny, tiny_config, tiny_model

    cfg = tiny_config("chairs", "none")
    path = save_tiny(tmp_path / "plain.safetensors", cfg)
    with_global = apply_overrides(cfg, ["--model.global_features", "true"])
    model = PixelNeRF(with_global.model, depth_aware=False)
    record = warm_start(model, str(path), with_global.model, depth_aware=False)
    assert record.step == 7
    assert all(torch.count_nonzero(t) == 0 for k, t in model.state_dict().items() if "lin_global" in k)
    source = tiny_model(cfg).eval()
    model.eval()
    src = sources(b=2, v=1, size=16)
    pts, dirs = query(b=2)
    with torch.no_grad():
        for which in ("coarse", "fine"):
            got = model.field(model.encode(src), which)(pts, dirs)
            want = source.field(source.encode(src), which)(pts, dirs)
            for a, b in zip(got, want, strict=True):
                torch.testing.assert_close(a, b, rtol=0, atol=0)
    model.train()
    rgb, sigma = model.field(model.encode(src), "fine")(pts, dirs)
    (rgb.sum() + sigma.sum()).backward()
    assert model.fine.lin_global.weight.grad.abs().sum() > 0
    global_path = save_tiny(tmp_path / "global.safetensors", with_global)
    with pytest.raises(DepthnerfError, match="model.global_features = True, the run False"):
        warm_start(PixelNeRF(cfg.model, depth_aware=False), str(global_path), cfg.model, depth_aware=False)


def test_checkpoint_with_global_features_evaluates_and_reconstructs(tmp_path):
    """A global-feature checkpoint loads from its weights alone, is evaluated (the summary's method names the
    option) and reconstructs a photo."""
    import json

    from PIL import Image

    from depthnerf.cli import main
    from depthnerf.config_io import apply_overrides
    from tests.fixtures_checkpoints import save_tiny, tiny_config
    from tests.fixtures_srn import make_srn_fixture

    root = make_srn_fixture(tmp_path / "data", "chairs", splits={"test": 1}, views=3, size=16)
    cfg = apply_overrides(tiny_config("chairs", "none"), ["--model.global_features", "true"])
    ckpt = save_tiny(tmp_path / "global.safetensors", cfg)
    assert main(["eval", "--checkpoint", str(ckpt), "--data", str(root), "--out", str(tmp_path / "ev"),
                 "--no-mesh", "--no-progress"]) == 0
    summary = json.loads((tmp_path / "ev" / "summary.json").read_text())
    assert summary["method"].endswith(" + global features")
    assert 5 < summary["psnr"] < 60
    photo = next((root / "chairs_test").glob("*/rgb/*.png"))
    Image.open(photo).save(tmp_path / "chair.png")
    assert main(["reconstruct", str(tmp_path / "chair.png"), "--checkpoint", str(ckpt), "--out",
                 str(tmp_path / "rec"), "--views", "2", "--mesh-resolution", "0", "--facing", "none"]) == 0
    assert (tmp_path / "rec" / "manifest.json").is_file()
