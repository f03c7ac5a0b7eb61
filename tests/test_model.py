"""Model tests: projection + pixel-aligned sampling, positional encoding, brute-force reference of the whole field
(multi-view mean pooling), the lin_z-on-map optimisation, statelessness, baseline vs depth-aware."""

from __future__ import annotations

import math

import pytest
import torch

from depthnerf.data.cameras import look_at, project, world_to_camera
from depthnerf.model import EncodedViews, EncoderConfig, FieldConfig, PixelNeRF, PixelNeRFConfig, SourceViews
from depthnerf.model.features import project_points, sample_projected, to_source_frames, uv_to_grid
from depthnerf.model.field import PositionalEncoding

SMALL_FIELD = FieldConfig(d_hidden=32, chunk_points=7)


def small_config(**field_kw) -> PixelNeRFConfig:
    field = FieldConfig(**{**SMALL_FIELD.__dict__, **field_kw})
    return PixelNeRFConfig(encoder=EncoderConfig(backbone="resnet18"), coarse=field, fine=field)


def randomize(model: torch.nn.Module, seed: int = 0) -> torch.nn.Module:
    """Non-trivial weights everywhere (pixelNeRF zero-inits fc_1, which would hide bugs in the blocks)."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in model.named_parameters():
            if name.startswith("coarse") or name.startswith("fine"):
                p.copy_(torch.randn(p.shape, generator=gen) / math.sqrt(p.shape[-1]))
    return model.eval()


def sources(b: int = 2, v: int = 1, size: int = 32, seed: int = 0, prior: bool = False) -> SourceViews:
    gen = torch.Generator().manual_seed(seed)
    az = torch.rand(b, v, generator=gen) * 2 * math.pi
    eye = torch.stack([1.3 * torch.cos(az), 1.3 * torch.sin(az), 0.3 + 0.4 * torch.rand(b, v, generator=gen)], -1)
    focal = torch.full((b,), size * 131.25 / 128)
    principal = torch.full((b, 2), (size - 1) / 2)
    return SourceViews(images=torch.rand(b, v, 3, size, size, generator=gen), poses=look_at(eye), focal=focal,
                       principal=principal,
                       disparity=torch.rand(b, v, 1, size, size, generator=gen) if prior else None)


def query(b: int = 2, r: int = 5, s: int = 4, seed: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    pts = (torch.rand(b, r, s, 3, generator=gen) - 0.5) * 0.8
    dirs = torch.nn.functional.normalize(torch.randn(b, r, 3, generator=gen), dim=-1)
    return pts, dirs


# --- projection and pixel-aligned sampling ----------------------------------------------------------------------

def test_known_point_projects_to_its_pixel_and_samples_its_feature():
    h = w = 16
    focal, cx, cy = 20.0, 7.5, 7.5
    c2w = look_at(torch.tensor([[0.3, -1.2, 0.5]]))  # [1 4 4]
    i, j, z = 3, 11, 1.1  # pixel centre (u, v) = (j, i) at z-depth 1.1
    x_cam = torch.tensor([(j - cx) / focal * z, (i - cy) / focal * z, z])
    world = c2w[0, :3, :3] @ x_cam + c2w[0, :3, 3]
    w2c = torch.linalg.inv(c2w)[:, None]  # [B=1 V=1 4 4]
    rotated, cam = to_source_frames(world[None, None], w2c)
    torch.testing.assert_close(cam[0, 0, 0], x_cam, atol=1e-5, rtol=0)
    torch.testing.assert_close(cam[0, 0], world_to_camera(world[None], c2w[0]), atol=1e-5, rtol=0)
    torch.testing.assert_close(rotated[0, 0, 0], c2w[0, :3, :3].T @ world, atol=1e-5, rtol=0)
    uv = project_points(cam, torch.tensor([focal]), torch.tensor([[cx, cy]]))
    torch.testing.assert_close(uv[0, 0, 0], torch.tensor([float(j), float(i)]), atol=1e-4, rtol=0)
    torch.testing.assert_close(uv[0, 0], project(cam[0, 0], focal, (cx, cy)), atol=1e-5, rtol=0)
    # The model's intrinsics come in the features' dtype (bf16 under autocast): the projection promotes them to the
    # camera points' float32 (it does not round the points to bf16), and its values are cameras.project's.
    focal_bf16, principal_bf16 = torch.tensor([focal], dtype=torch.bfloat16), torch.tensor([[cx, cy]]).bfloat16()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        uv_bf16 = project_points(cam, focal_bf16, principal_bf16)
    assert uv_bf16.dtype == torch.float32
    assert torch.equal(uv_bf16, project(cam, focal_bf16[:, None], principal_bf16[:, None]))
    # A full-resolution map whose pixel (r, c) stores (c, r): sampling returns the pixel coordinates.
    rows, cols = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32),
                                indexing="ij")
    coord_map = torch.stack([cols, rows], -1)[None, None]  # [1 1 H W 2] channels-last
    feat = sample_projected(coord_map, uv, (h, w))
    torch.testing.assert_close(feat[0, 0, 0], torch.tensor([float(j), float(i)]), atol=1e-4, rtol=0)


def test_latent_scaling_matches_pixelnerf_formula():
    """pixelNeRF: scale = (Wf, Hf) / (Wf - 1, Hf - 1) * 2; grid = uv * scale / (W, H) - 1 (align_corners=True),
    i.e. feature column u * Wf / W; a half-resolution map storing its own pixel coordinates returns those."""
    h, w, hf, wf = 32, 24, 16, 12
    gen = torch.Generator().manual_seed(0)
    uv = torch.rand(1, 1, 50, 2, generator=gen) * torch.tensor([w - 2.0, h - 2.0])  # inside the image
    expected_grid = uv * (torch.tensor([wf, hf]) / torch.tensor([wf - 1.0, hf - 1.0]) * 2) / torch.tensor([w, h]) - 1
    torch.testing.assert_close(uv_to_grid(uv, (h, w), (hf, wf)), expected_grid)
    rows, cols = torch.meshgrid(torch.arange(hf, dtype=torch.float32), torch.arange(wf, dtype=torch.float32),
                                indexing="ij")
    coord_map = torch.stack([cols, rows], -1)[None, None]
    # camera points that project exactly to uv with f = 10, c = (0, 0), z = 2
    cam = torch.cat([uv / 10 * 2, torch.full_like(uv[..., :1], 2.0)], dim=-1)
    feat = sample_projected(coord_map, project_points(cam, torch.tensor([10.0]), torch.zeros(1, 2)), (h, w))
    torch.testing.assert_close(feat, uv * torch.tensor([wf / w, hf / h]), atol=1e-4, rtol=0)
    # border padding: far outside the image reads the edge features
    far_cam = torch.tensor([[[[-50.0, 500.0, 1.0]]]])
    edge = sample_projected(coord_map, project_points(far_cam, torch.tensor([10.0]), torch.zeros(1, 2)), (h, w))
    torch.testing.assert_close(edge[0, 0, 0], torch.tensor([0.0, hf - 1.0]))


def test_positional_encoding_closed_form():
    pe = PositionalEncoding(num_freqs=6, freq_factor=1.5, include_input=True)
    assert pe(torch.zeros(2, 3)).shape == (2, FieldConfig().d_encoding) == (2, 39) and FieldConfig().d_in == 42
    x = torch.tensor([[0.1, -0.7, 0.33], [1.0, 0.0, -2.0]])
    out = pe(x)
    assert out.shape == (2, 39)
    for n in range(2):
        expected = list(x[n])
        for k in range(6):
            f = 1.5 * 2.0 ** k
            expected += [math.sin(f * float(c)) for c in x[n]] + [math.cos(f * float(c)) for c in x[n]]
        torch.testing.assert_close(out[n], torch.tensor(expected), atol=1e-5, rtol=0)


def test_density_bias_init_makes_the_initial_density_that_constant():
    """``density_bias_init = b``: lin_out's density row starts at zero weights and bias b, so the raw density
    output is b at every input (whatever the other weights), while the colour logits still vary."""
    from depthnerf.model.field import ResidualField

    torch.manual_seed(0)
    cfg = FieldConfig(d_hidden=16, n_blocks=2, combine_layer=1, density_bias_init=0.75)
    mlp = ResidualField(cfg, d_latent=8)
    with torch.no_grad():
        for block in mlp.blocks:  # non-identity blocks
            block.fc_1.weight.normal_(0, 0.3)
        raw = mlp(torch.randn(1, 1, 30, cfg.d_in), torch.randn(1, 1, 30, 8), projected=False)
    assert torch.equal(raw[..., 3], torch.full((1, 30), 0.75))
    assert raw[..., :3].std() > 0.1


# --- brute-force reference of the whole field -------------------------------------------------------------------

def bilinear_border(fmap: torch.Tensor, fx: float, fy: float) -> torch.Tensor:
    """Reference bilinear lookup at continuous feature pixel (fx, fy) with coordinates clamped to the map."""
    _, hf, wf = fmap.shape
    fx, fy = min(max(fx, 0.0), wf - 1.0), min(max(fy, 0.0), hf - 1.0)
    x0, y0 = min(int(math.floor(fx)), wf - 2), min(int(math.floor(fy)), hf - 2)
    ax, ay = fx - x0, fy - y0
    return ((1 - ax) * (1 - ay) * fmap[:, y0, x0] + ax * (1 - ay) * fmap[:, y0, x0 + 1]
            + (1 - ax) * ay * fmap[:, y0 + 1, x0] + ax * ay * fmap[:, y0 + 1, x0 + 1])


def reference_field(model: PixelNeRF, enc: EncodedViews, src: SourceViews, which: str, pts, dirs):
    """Point-by-point, view-by-view evaluation written from the pixelNeRF description."""
    mlp = model.network(which)
    b, v, _, hf, wf = enc.features.shape
    h, w = enc.image_size
    rgb = torch.zeros(*pts.shape)
    sigma = torch.zeros(pts.shape[:-1])
    for bi in range(b):
        for ri in range(pts.shape[1]):
            for si in range(pts.shape[2]):
                hidden = []
                for vi in range(v):
                    c2w = src.poses[bi, vi]
                    cam = world_to_camera(pts[bi, ri, si][None], c2w)[0]
                    u, vv = project(cam[None], float(src.focal[bi]), tuple(src.principal[bi].tolist()))[0]
                    feat = bilinear_border(enc.features[bi, vi], float(u) * wf / w, float(vv) * hf / h)
                    rot = c2w[:3, :3].T
                    coords = rot @ pts[bi, ri, si] if mlp.cfg.point_frame == "rotated" else cam
                    x_in = torch.cat([mlp.encoding(coords), rot @ dirs[bi, ri]])
                    x = mlp.lin_in(x_in)
                    for k in range(mlp.cfg.combine_layer):
                        x = x + mlp.lin_z[k](feat)
                        blk = mlp.blocks[k]
                        x = x + blk.fc_1(torch.relu(blk.fc_0(torch.relu(x))))
                    hidden.append(x)
                x = torch.stack(hidden).mean(0)
                for blk in mlp.blocks[mlp.cfg.combine_layer:]:
                    x = x + blk.fc_1(torch.relu(blk.fc_0(torch.relu(x))))
                out = mlp.lin_out(torch.relu(x))
                rgb[bi, ri, si] = torch.sigmoid(out[:3])
                sigma[bi, ri, si] = torch.relu(out[3])
    return rgb, sigma


@pytest.mark.parametrize(("views", "image_scale", "frame", "combine"),
                         [(1, 1.0, "rotated", 3), (2, 1.0, "rotated", 3), (1, 0.5, "camera", 3), (2, 1.0, "rotated", 5)])
def test_field_matches_bruteforce_reference(views, image_scale, frame, combine):
    torch.manual_seed(0)
    cfg = small_config(point_frame=frame, combine_layer=combine)
    cfg.encoder.image_scale = image_scale
    model = randomize(PixelNeRF(cfg, depth_aware=False))
    src = sources(b=2, v=views, size=48)
    pts, dirs = query(b=2, r=3, s=4)
    pts[0, 0, 0] = torch.tensor([5.0, -4.0, 3.0])  # projects outside the image: border features
    with torch.no_grad():
        enc = model.encode(src)
        for which in ("coarse", "fine"):
            assert enc.features.shape[-2:] == (int(24 * image_scale), int(24 * image_scale))
            rgb, sigma = model.field(enc, which)(pts, dirs)
            ref_rgb, ref_sigma = reference_field(model, enc, src, which, pts, dirs)
            torch.testing.assert_close(rgb, ref_rgb, atol=1e-5, rtol=1e-4)
            torch.testing.assert_close(sigma, ref_sigma, atol=1e-5, rtol=1e-4)
    assert (sigma > 0).any() and (rgb.std() > 1e-3)  # not a degenerate comparison


def test_multiview_pools_views():
    torch.manual_seed(0)
    model = randomize(PixelNeRF(small_config(), depth_aware=False))
    two = sources(b=1, v=2, seed=3)
    pts, dirs = query(b=1)
    with torch.no_grad():
        out2 = model.field(model.encode(two), "coarse")(pts, dirs)
        firsts = [SourceViews(two.images[:, k:k + 1], two.poses[:, k:k + 1], two.focal, two.principal)
                  for k in range(2)]
        out1 = [model.field(model.encode(s), "coarse")(pts, dirs) for s in firsts]
        dup = SourceViews(two.images[:, :1].repeat(1, 2, 1, 1, 1), two.poses[:, :1].repeat(1, 2, 1, 1),
                          two.focal, two.principal)
        out_dup = model.field(model.encode(dup), "coarse")(pts, dirs)
    torch.testing.assert_close(out_dup[0], out1[0][0], atol=1e-5, rtol=1e-4)  # mean of identical views
    assert (out2[0] - out1[0][0]).abs().max() > 1e-3 and (out2[0] - out1[1][0]).abs().max() > 1e-3


# --- lin_z on the map ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("views", [1, 2])
def test_lin_z_on_map_equals_per_point(views):
    torch.manual_seed(0)
    per_point = randomize(PixelNeRF(small_config(lin_z_on_map=False), depth_aware=False), seed=5)
    on_map = PixelNeRF(small_config(lin_z_on_map=True), depth_aware=False)
    on_map.load_state_dict(per_point.state_dict())
    on_map.eval()
    src = sources(b=2, v=views, seed=2)
    pts, dirs = query(b=2, r=6, s=5)
    pts[1, 2] *= 8.0  # some points outside the image (border padding keeps the identity exact)
    results = []
    for model in (per_point, on_map):
        model.zero_grad()
        rgb, sigma = model.field(model.encode(src), "coarse")(pts, dirs)
        (rgb.square().sum() + sigma.sum()).backward()
        results.append((rgb, sigma, {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None}))
    torch.testing.assert_close(results[1][0], results[0][0], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(results[1][1], results[0][1], atol=1e-5, rtol=1e-5)
    assert results[0][2].keys() == results[1][2].keys()
    for name, grad in results[0][2].items():
        torch.testing.assert_close(results[1][2][name], grad, atol=1e-4, rtol=1e-3, msg=name)
    with torch.no_grad():  # chunked inference path (chunk_points=7 < 30 points) agrees too
        rgb_c, sigma_c = on_map.field(on_map.encode(src), "coarse")(pts, dirs)
    torch.testing.assert_close(rgb_c, results[0][0], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(sigma_c, results[0][1], atol=1e-5, rtol=1e-5)


# --- statelessness ------------------------------------------------------------------------------------------------

def test_encode_is_stateless_and_encodings_interleave():
    torch.manual_seed(0)
    model = randomize(PixelNeRF(small_config(), depth_aware=False))
    before = {k: v.clone() for k, v in model.state_dict().items()}
    pts, dirs = query(b=1)
    with torch.no_grad():
        enc_a, enc_b = model.encode(sources(b=1, seed=10)), model.encode(sources(b=1, seed=11))
        assert isinstance(enc_a, EncodedViews) and enc_a.features.shape[:3] == (1, 1, 256 + 128 + 64 + 64)
        fa, fb = model.field(enc_a, "fine"), model.field(enc_b, "fine")
        a1, b1, a2 = fa(pts, dirs), fb(pts, dirs), fa(pts, dirs)
        fresh = PixelNeRF(small_config(), depth_aware=False)
        fresh.load_state_dict(model.state_dict())
        a_fresh = fresh.eval().field(fresh.encode(sources(b=1, seed=10)), "fine")(pts, dirs)
    torch.testing.assert_close(a1[0], a2[0], rtol=0, atol=0)
    torch.testing.assert_close(a1[0], a_fresh[0], rtol=0, atol=0)
    assert (a1[0] - b1[0]).abs().max() > 1e-3
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())
    assert not [n for n, _ in model.named_buffers() if "latent" in n]


# --- baseline vs depth-aware --------------------------------------------------------------------------------------

def test_depth_variant_differs_only_in_encoder_input():
    base, deep = PixelNeRF(small_config(), depth_aware=False), PixelNeRF(small_config(), depth_aware=True)
    shapes_b = {n: tuple(p.shape) for n, p in base.named_parameters()}
    shapes_d = {n: tuple(p.shape) for n, p in deep.named_parameters()}
    extra = sorted(set(shapes_d) - set(shapes_b))
    assert not set(shapes_b) - set(shapes_d)
    assert extra and all(n.startswith("encoder.depth.") for n in extra)
    cd = deep.cfg.encoder.depth_channels
    differ = {n for n in shapes_b if shapes_b[n] != shapes_d[n]}
    assert differ == {"encoder.trunk.conv1.weight"} | {f"{net}.lin_z.{k}.weight" for net in ("coarse", "fine")
                                                       for k in range(3)}
    assert shapes_b["encoder.trunk.conv1.weight"] == (64, 3, 7, 7)
    assert shapes_d["encoder.trunk.conv1.weight"] == (64, 4, 7, 7)
    assert shapes_d["coarse.lin_z.0.weight"][1] == shapes_b["coarse.lin_z.0.weight"][1] + cd == 512 + cd
    n_depth = sum(p.numel() for n, p in deep.named_parameters() if n.startswith("encoder.depth."))
    assert n_depth == 1 * 32 * 9 + 32 * 32 * 9 + 32 * cd * 9 + 2 * (32 + 32 + cd)
    # random-init conv1: the 4th input channel is the mean of the RGB kernels
    w = deep.encoder.trunk.conv1.weight
    torch.testing.assert_close(w[:, 3], w[:, :3].mean(1))


def test_depth_model_with_ablated_depth_inputs_equals_baseline():
    """Copy the baseline's weights into the depth model, zero the prior's conv1 kernel and the lin_z columns of the
    depth features: whatever the prior, the depth model computes exactly the baseline's function."""
    torch.manual_seed(0)
    base = randomize(PixelNeRF(small_config(), depth_aware=False))
    deep = PixelNeRF(small_config(), depth_aware=True).eval()
    state = deep.state_dict()
    for name, value in base.state_dict().items():
        if name == "encoder.trunk.conv1.weight":
            value = torch.cat([value, torch.zeros_like(value[:, :1])], dim=1)
        elif ".lin_z." in name and name.endswith("weight"):
            value = torch.cat([value, torch.zeros(value.shape[0], state[name].shape[1] - value.shape[1])], dim=1)
        state[name] = value
    deep.load_state_dict(state)
    src = sources(b=2, v=1, prior=True)
    pts, dirs = query(b=2)
    with torch.no_grad():
        out_b = base.field(base.encode(src), "coarse")(pts, dirs)
        out_d = deep.field(deep.encode(src), "coarse")(pts, dirs)
        src.disparity = 1.0 - src.disparity
        out_d2 = deep.field(deep.encode(src), "coarse")(pts, dirs)
    for a, b, c in zip(out_b, out_d, out_d2, strict=True):
        torch.testing.assert_close(b, a, atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(c, a, atol=1e-5, rtol=1e-5)


def test_depth_model_requires_prior():
    from depthnerf.errors import DepthnerfError

    model = PixelNeRF(small_config(), depth_aware=True).eval()
    with pytest.raises(DepthnerfError, match="prior"):
        model.encode(sources(b=1, prior=False))


# --- optional pretrained trunk weights ----------------------------------------------------------------------------

class _NotATensor:
    pass


def test_pretrained_weights_load_from_local_files(tmp_path):
    import torchvision
    from safetensors.torch import save_file

    from depthnerf.errors import DepthnerfError
    from depthnerf.model.encoder import ImageEncoder

    torch.manual_seed(3)
    state = {k: v.contiguous() for k, v in torchvision.models.resnet34(weights=None).state_dict().items()}
    save_file(state, str(tmp_path / "r34.safetensors"))
    torch.save(state, tmp_path / "r34.pth")
    base = ImageEncoder(EncoderConfig(pretrained_path=str(tmp_path / "r34.safetensors")), depth_aware=False)
    for key, value in base.trunk.state_dict().items():
        assert torch.equal(value, state[key]), key
    assert not any(k.startswith(("layer4", "fc")) for k in base.state_dict())
    deep = ImageEncoder(EncoderConfig(pretrained_path=str(tmp_path / "r34.pth")), depth_aware=True)
    w = deep.trunk.conv1.weight
    assert torch.equal(w[:, :3], state["conv1.weight"])
    torch.testing.assert_close(w[:, 3], state["conv1.weight"].mean(1))
    assert torch.equal(deep.trunk.layer3[5].conv2.weight, state["layer3.5.conv2.weight"])

    with pytest.raises(DepthnerfError, match="wrong backbone"):  # resnet34 weights into a resnet18 trunk
        ImageEncoder(EncoderConfig(backbone="resnet18", pretrained_path=str(tmp_path / "r34.pth")), depth_aware=False)
    (tmp_path / "junk.safetensors").write_bytes(b"not a safetensors file")
    with pytest.raises(DepthnerfError, match="junk.safetensors"):
        ImageEncoder(EncoderConfig(pretrained_path=str(tmp_path / "junk.safetensors")), depth_aware=False)
    torch.save({"conv1.weight": _NotATensor()}, tmp_path / "pickled.pth")  # needs unpickling: refused
    with pytest.raises(DepthnerfError, match="pickled.pth"):
        ImageEncoder(EncoderConfig(pretrained_path=str(tmp_path / "pickled.pth")), depth_aware=False)
    with pytest.raises(DepthnerfError, match="not found"):
        ImageEncoder(EncoderConfig(pretrained_path=str(tmp_path / "missing.pth")), depth_aware=False)


def test_image_statistics_at_inference_are_trainings_and_leave_the_buffers():
    from depthnerf.errors import DepthnerfError

    model = PixelNeRF(small_config(), depth_aware=True)
    src = sources(b=3, size=32, prior=True)
    state = {k: v.clone() for k, v in model.state_dict().items()}
    model.train()
    with torch.no_grad():
        trained = model.encode(src).features  # per-object statistics (and a running-statistics update)
    model.load_state_dict(state)
    model.eval()
    with torch.no_grad():
        image = model.encode(src, encoder_norm="image").features
        running = model.encode(src).features
        alone = torch.cat([model.encode(SourceViews(images=src.images[i:i + 1], poses=src.poses[i:i + 1],
                                                    focal=src.focal[i:i + 1], principal=src.principal[i:i + 1],
                                                    disparity=src.disparity[i:i + 1]), encoder_norm="image").features
                           for i in range(3)])
    torch.testing.assert_close(image, trained, rtol=0, atol=0)
    torch.testing.assert_close(alone, image, rtol=2e-3, atol=2e-3)  # float sums in another order, 3 stages deep
    assert not torch.allclose(running, image, atol=1e-2)
    assert all(torch.equal(v, state[k]) for k, v in model.state_dict().items())  # nothing updated
    with pytest.raises(DepthnerfError, match="encoder_norm must be one of running, image"):
        model.encode(src, encoder_norm="batch")


@pytest.mark.parametrize(("num_layers", "first_pool", "image_scale"),
                         [(4, True, 1.0), (3, True, 1.0), (4, False, 1.0), (1, True, 1.0), (4, True, 0.5)])
def test_deepest_side_is_the_trunks_last_stage(num_layers, first_pool, image_scale):
    """EncoderConfig.deepest_side (what training's resolution check uses) against the trunk run on real inputs."""
    from depthnerf.model.encoder import ResNetTrunk

    cfg = EncoderConfig(backbone="resnet18", num_layers=num_layers, use_first_pool=first_pool, image_scale=image_scale)
    trunk = ResNetTrunk(cfg, depth_aware=False).eval()
    for resolution in (8, 15, 16, 17, 23, 33, 64):
        x = torch.zeros(1, 3, resolution, resolution)
        if image_scale != 1.0:
            x = torch.nn.functional.interpolate(x, scale_factor=image_scale, mode="area", recompute_scale_factor=True)
        with torch.no_grad():
            last = trunk(x)[-1]
        assert last.shape[-2:] == (cfg.deepest_side(resolution),) * 2, resolution
