"""Official pixelNeRF weights in this package's baseline: the converted model against a reference of pixelNeRF's
forward pass written here from its definition (OpenGL camera axes, ``sin(f x + phase)`` encoding, ``ResnetFC``),
on random weights with pixelNeRF's tensor names; then the file checks and ``scripts/import_pixelnerf.py``."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F
import torchvision

from depthnerf.errors import DepthnerfError
from depthnerf.model.config import EncoderConfig, FieldConfig, PixelNeRFConfig
from depthnerf.model.pixelnerf import PixelNeRF, SourceViews
from depthnerf.pretrained.load import load_pretrained
from depthnerf.pretrained.official_pixelnerf import convert_official_state, input_signs, read_official_state
from depthnerf.state_dicts import load_state_strict

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import import_pixelnerf  # noqa: E402

HIDDEN, BLOCKS, COMBINE, FREQS = 32, 5, 3, 6
SIZE, FOCAL = 32, 40.0


def official_state(seed: int = 0, hidden: int = HIDDEN, backbone: str = "resnet18") -> dict[str, torch.Tensor]:
    """Random weights under pixelNeRF's names: its torchvision trunk (``layer4`` and ``fc`` included, as it builds
    them), two ``ResnetFC`` MLPs with every layer non-zero, and its encoding's buffers."""
    gen = torch.Generator().manual_seed(seed)
    trunk = getattr(torchvision.models, backbone)()
    with torch.no_grad():
        for m in trunk.modules():
            if isinstance(m, torch.nn.BatchNorm2d):  # eval-mode statistics that are not the identity
                m.running_mean.copy_(torch.rand(m.num_features, generator=gen) * 0.2 - 0.1)
                m.running_var.copy_(torch.rand(m.num_features, generator=gen) + 0.5)
                m.weight.copy_(torch.rand(m.num_features, generator=gen) + 0.5)
                m.bias.copy_(torch.rand(m.num_features, generator=gen) * 0.2 - 0.1)
    state = {f"encoder.model.{k}": v.clone() for k, v in trunk.state_dict().items()}
    latent = 512 if backbone in ("resnet18", "resnet34") else None
    d_in = 3 + 6 * FREQS + 3

    def linear(name: str, fan_out: int, fan_in: int) -> None:
        state[f"{name}.weight"] = torch.randn(fan_out, fan_in, generator=gen) / math.sqrt(fan_in)
        state[f"{name}.bias"] = torch.randn(fan_out, generator=gen) * 0.1

    for net in ("mlp_coarse", "mlp_fine"):
        linear(f"{net}.lin_in", hidden, d_in)
        for b in range(BLOCKS):
            linear(f"{net}.blocks.{b}.fc_0", hidden, hidden)
            linear(f"{net}.blocks.{b}.fc_1", hidden, hidden)
        for b in range(COMBINE):
            linear(f"{net}.lin_z.{b}", hidden, latent)
        linear(f"{net}.lin_out", 4, hidden)
        state[f"{net}.lin_out.bias"][3] = 2.0  # density alive at most points, so sigma is compared too
    freqs = 1.5 * 2.0 ** torch.arange(FREQS, dtype=torch.float32)
    state["code._freqs"] = torch.repeat_interleave(freqs, 2).view(1, -1, 1)
    state["code._phases"] = torch.tensor([0.0, math.pi / 2] * FREQS).view(1, -1, 1)
    return state


def reference_query(state: dict[str, torch.Tensor], net: str, image: torch.Tensor, pose_cv: torch.Tensor,
                    points: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """pixelNeRF's (rgb, sigma) at ``points`` seen from one source view, from its definition: poses in OpenGL
    camera axes (SRN's times diag(1, -1, -1, 1)), ``uv = -xy / z * (f, -f) + c``, features sampled with
    ``latent_scaling``, encoding ``[x, sin(f_k x + 0), sin(f_k x + pi/2), ...]``, latent added before the first
    ``COMBINE`` blocks."""
    trunk = torchvision.models.resnet18()
    trunk.load_state_dict({k[len("encoder.model."):]: v for k, v in state.items() if k.startswith("encoder.model.")})
    trunk.eval()
    with torch.no_grad():
        x = image[None] * 2 - 1
        stages = [trunk.relu(trunk.bn1(trunk.conv1(x)))]
        stages.append(trunk.layer1(trunk.maxpool(stages[0])))
        stages.append(trunk.layer2(stages[1]))
        stages.append(trunk.layer3(stages[2]))
        size = stages[0].shape[-2:]
        latent = torch.cat([F.interpolate(s, size, mode="bilinear", align_corners=True) for s in stages], 1)
        pose_gl = pose_cv @ torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0]))
        rot = pose_gl[:3, :3].T
        trans = -rot @ pose_gl[:3, 3]
        xyz_rot = points @ rot.T
        xyz = xyz_rot + trans
        uv = -xyz[:, :2] / xyz[:, 2:] * torch.tensor([FOCAL, -FOCAL]) + torch.tensor([SIZE / 2, SIZE / 2])
        wl, hl = latent.shape[-1], latent.shape[-2]
        scaling = torch.tensor([wl / (wl - 1) * 2, hl / (hl - 1) * 2])
        grid = uv * scaling / torch.tensor([SIZE, SIZE]) - 1
        z = F.grid_sample(latent, grid[None, :, None], align_corners=True, padding_mode="border")[0, :, :, 0].T
        parts = [xyz_rot]
        for k in range(FREQS):
            for phase in (0.0, math.pi / 2):
                parts.append(torch.sin(1.5 * 2**k * xyz_rot + phase))
        parts.append(dirs @ rot.T)
        h = F.linear(torch.cat(parts, -1), state[f"{net}.lin_in.weight"], state[f"{net}.lin_in.bias"])
        for b in range(BLOCKS):
            if b < COMBINE:
                h = h + F.linear(z, state[f"{net}.lin_z.{b}.weight"], state[f"{net}.lin_z.{b}.bias"])
            inner = F.linear(F.relu(h), state[f"{net}.blocks.{b}.fc_0.weight"], state[f"{net}.blocks.{b}.fc_0.bias"])
            h = h + F.linear(F.relu(inner), state[f"{net}.blocks.{b}.fc_1.weight"],
                             state[f"{net}.blocks.{b}.fc_1.bias"])
        out = F.linear(F.relu(h), state[f"{net}.lin_out.weight"], state[f"{net}.lin_out.bias"])
    return torch.sigmoid(out[:, :3]), F.relu(out[:, 3])


def small_config() -> PixelNeRFConfig:
    field = FieldConfig(d_hidden=HIDDEN, n_blocks=BLOCKS, combine_layer=COMBINE)
    return PixelNeRFConfig(encoder=EncoderConfig(backbone="resnet18"), coarse=field, fine=field)


def camera() -> torch.Tensor:
    """An OpenCV camera-to-world pose 1.3 from the origin, looking at it, +z up (SRN-like)."""
    eye = torch.tensor([1.0, -0.6, 0.5])
    eye = eye / eye.norm() * 1.3
    forward = -eye / eye.norm()
    right = torch.linalg.cross(forward, torch.tensor([0.0, 0.0, 1.0]))
    right = right / right.norm()
    down = torch.linalg.cross(forward, right)
    pose = torch.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, down, forward, eye
    return pose


def queries(model: PixelNeRF, which: str, image: torch.Tensor, pose: torch.Tensor, points: torch.Tensor,
            dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    src = SourceViews(images=image[None, None], poses=pose[None, None], focal=torch.tensor([FOCAL]),
                      principal=torch.tensor([[SIZE / 2, SIZE / 2]]))
    with torch.no_grad():
        rgb, sigma = model.field(model.encode(src), which)(points[None, :, None], dirs[None])
    return rgb[0, :, 0], sigma[0, :, 0]


@pytest.fixture(scope="module")
def scene() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(1)
    image = torch.rand(3, SIZE, SIZE, generator=gen)
    points = torch.rand(200, 3, generator=gen) * 0.8 - 0.4  # most project inside, some onto the border
    dirs = F.normalize(torch.randn(200, 3, generator=gen), dim=-1)
    return image, camera(), points, dirs


@pytest.mark.parametrize("which", ["coarse", "fine"])
def test_converted_model_computes_pixelnerfs_function(scene, which):
    image, pose, points, dirs = scene
    official = official_state()
    model = PixelNeRF(small_config(), depth_aware=False)
    load_state_strict(model, convert_official_state(official, small_config(), Path("w")), Path("w"))
    model.eval()
    rgb, sigma = queries(model, which, image, pose, points, dirs)
    ref_rgb, ref_sigma = reference_query(official, f"mlp_{which}", image, pose, points, dirs)
    assert float(ref_sigma.gt(0).float().mean()) > 0.5 and float(ref_rgb.std()) > 0.02  # a non-trivial field
    torch.testing.assert_close(rgb, ref_rgb, atol=2e-5, rtol=1e-4)
    torch.testing.assert_close(sigma, ref_sigma, atol=2e-5, rtol=1e-4)

    renamed = {k: v for k, v in convert_official_state(official, small_config(), Path("w")).items()}
    renamed[f"{which}.lin_in.weight"] = official[f"mlp_{which}.lin_in.weight"]  # the names alone, no axis flip
    load_state_strict(model, renamed, Path("w"))
    rgb_names_only, _ = queries(model, which, image, pose, points, dirs)
    assert float((rgb_names_only - ref_rgb).abs().max()) > 1e-2  # the camera-axes flip is what makes it equal


def test_input_signs_flip_y_and_z_of_coordinates_sines_and_directions():
    signs = input_signs(FieldConfig()).tolist()
    flip, keep = [1.0, -1.0, -1.0], [1.0, 1.0, 1.0]
    assert signs == flip + (flip + keep) * 6 + flip
    assert input_signs(FieldConfig(include_input=False, use_viewdirs=False, num_freqs=1)).tolist() == flip + keep


def test_file_round_trip_and_what_is_refused(tmp_path):
    official = official_state()
    path = tmp_path / "pixel_nerf_latest"
    torch.save(official, path)
    assert set(read_official_state(path)) == set(official)
    cfg = small_config()
    bad_freqs = {**official, "code._freqs": official["code._freqs"] * 2}
    with pytest.raises(DepthnerfError, match="code._freqs"):
        convert_official_state(bad_freqs, cfg, path)
    with pytest.raises(DepthnerfError, match="global_encoder.model.conv1.weight"):
        convert_official_state({**official, "global_encoder.model.conv1.weight": torch.zeros(1)}, cfg, path)
    wide = official_state(hidden=HIDDEN * 2)
    model = PixelNeRF(cfg, depth_aware=False)
    with pytest.raises(DepthnerfError, match=r"pixel_nerf_latest: .*shape mismatch"):
        load_state_strict(model, convert_official_state(wide, cfg, path), path)
    missing = {k: v for k, v in official.items() if not k.startswith("mlp_fine.lin_z.2")}
    with pytest.raises(DepthnerfError, match=r"missing 2 tensors \(e.g. fine.lin_z.2"):
        load_state_strict(model, convert_official_state(missing, cfg, path), path)
    with pytest.raises(DepthnerfError, match="not found"):
        read_official_state(tmp_path / "absent")
    (tmp_path / "junk").write_bytes(b"not a torch file")
    with pytest.raises(DepthnerfError, match="junk: cannot read official pixelNeRF weights"):
        read_official_state(tmp_path / "junk")
    torch.save({"model": official}, tmp_path / "nested")  # a dict of dicts: not a state dict
    with pytest.raises(DepthnerfError, match="nested: not a state dict of tensors"):
        read_official_state(tmp_path / "nested")


def test_import_script_writes_a_checkpoint_that_loads_as_the_baseline(tmp_path, capsys):
    """The script on the ``cpu-cars`` network (ResNet18, width 64): the same conversion as the paper preset's,
    small enough for a test."""
    official = official_state(hidden=64)
    weights, out = tmp_path / "pixel_nerf_latest", tmp_path / "converted.safetensors"
    torch.save(official, weights)
    assert import_pixelnerf.main(["--weights", str(weights), "--category", "cars", "--out", str(out),
                                  "--preset", "cpu-cars"]) == 0
    assert "depthnerf eval --checkpoint" in capsys.readouterr().out
    loaded = load_pretrained(out)
    assert not loaded.spec.depth_aware and loaded.spec.category == "cars" and loaded.spec.framing == "srn"
    assert loaded.spec.preset == "cpu-cars" and (loaded.spec.z_near, loaded.spec.z_far) == (0.8, 1.8)
    expected = convert_official_state(official, loaded.spec.model, weights)
    for key, value in loaded.model.state_dict().items():
        torch.testing.assert_close(value, expected[key].to(value.dtype), rtol=0, atol=0)
    assert import_pixelnerf.main(["--weights", str(weights), "--category", "chairs", "--out", str(out),
                                  "--preset", "cpu-cars"]) == 2
    assert "--preset cpu-cars is for cars, not --category chairs" in capsys.readouterr().err
