"""``--model.encoder.norm_stats``: whose statistics the encoder's BatchNorm layers normalise with in training."""

from __future__ import annotations

import pytest
import torch

from depthnerf.errors import DepthnerfError
from depthnerf.model.config import EncoderConfig
from depthnerf.model.encoder import ImageEncoder
from depthnerf.model.norm import ObjectBatchNorm2d, object_groups


def two_tone(contrast: torch.Tensor, channels: int = 3) -> torch.Tensor:
    """One object's features ``w_c + contrast_c * m``: a background level per channel and the object's difference
    from it on a shared pattern ``m`` (the first conv of a one-colour object on white, away from the border)."""
    m = torch.zeros(6, 7, dtype=torch.float64)
    m[1:4, 2:6] = 1.0
    m[2, 3] = 0.5
    background = torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)[:channels]
    return (background[:, None, None] + contrast[:, None, None] * m)[None]


def test_object_statistics_keep_only_the_sign_of_an_objects_contrast_and_batch_statistics_keep_its_size():
    """The closed form behind ``EncoderConfig.norm_stats``: normalised with its own moments, a two-tone image's
    channel ``w + a m`` becomes ``sign(a) (m - mean m) / std m``, so objects whose contrasts differ in size but not
    in sign (a pale and a deep colour of the same hue) get the same features; pooled over a batch they do not."""
    bn = ObjectBatchNorm2d(3, eps=1e-30).double().train()  # torch refuses eps 0 in training
    pale = torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64)
    deep = torch.tensor([1.2, -0.9, 0.25], dtype=torch.float64)
    x = torch.cat([two_tone(pale), two_tone(deep)])
    per_object = bn(x, object_groups(bn, 2))
    m = two_tone(torch.ones(3, dtype=torch.float64))[0, 0] - 1.0
    closed_form = (m - m.mean()) / m.std(unbiased=False)
    for k, contrast in enumerate((pale, deep)):
        for c in range(3):
            torch.testing.assert_close(per_object[k, c], torch.sign(contrast[c]) * closed_form, rtol=1e-12,
                                       atol=1e-12)
    pooled = bn(x, object_groups(bn, 1))
    assert (pooled[0] - pooled[1]).abs().max() > 0.5


def test_batch_statistics_pool_every_image_of_the_call():
    """In training mode with ``norm_stats="batch"`` the trunk's first BatchNorm normalises each channel with the
    mean and biased variance over all ``objects * V`` images (a loop over channels), and the features differ from
    those of per-object statistics; in evaluation mode (running statistics) the setting changes nothing."""
    torch.manual_seed(0)
    pooled = ImageEncoder(EncoderConfig(backbone="resnet18", num_layers=2, norm_stats="batch"), True)
    own = ImageEncoder(EncoderConfig(backbone="resnet18", num_layers=2), True)
    own.load_state_dict(pooled.state_dict())
    seen = {}
    pooled.trunk.bn1.register_forward_hook(lambda _m, args, out: seen.update(x=args[0], out=out.clone()))
    images, disparity = torch.rand(6, 3, 16, 16), torch.randn(6, 1, 16, 16)
    feats = pooled.train()(images, disparity, objects=3)
    bn = pooled.trunk.bn1
    for c in range(bn.num_features):
        values = seen["x"][:, c]
        mean = values.mean()
        var = ((values - mean) ** 2).mean()
        want = (values - mean) / torch.sqrt(var + bn.eps) * bn.weight[c] + bn.bias[c]
        torch.testing.assert_close(seen["out"][:, c], want, rtol=1e-4, atol=1e-5)
    assert (feats - own.train()(images, disparity, objects=3)).abs().max() > 1e-3
    own.load_state_dict(pooled.state_dict())  # the running statistics: pooled ones were folded in
    with torch.no_grad():
        torch.testing.assert_close(pooled.eval()(images, disparity, objects=3), own.eval()(images, disparity,
                                                                                          objects=3))


def test_norm_stats_is_checked():
    with pytest.raises(DepthnerfError, match="encoder.norm_stats must be one of object, batch"):
        EncoderConfig(norm_stats="instance")


def test_warm_start_may_change_the_training_statistics(tmp_path):
    """``--init-from`` across ``norm_stats`` loads the weights unchanged (a setting of training alone)."""
    from depthnerf.config_io import apply_overrides
    from depthnerf.model.pixelnerf import PixelNeRF
    from depthnerf.train.warm_start import warm_start
    from tests.fixtures_checkpoints import save_tiny, tiny_config, tiny_model

    cfg = tiny_config("chairs", "none")
    path = save_tiny(tmp_path / "object.safetensors", cfg)
    pooled = apply_overrides(cfg, ["--model.encoder.norm_stats", "batch"])
    model = PixelNeRF(pooled.model, depth_aware=False)
    warm_start(model, str(path), pooled.model, depth_aware=False)
    for (name, got), want in zip(model.state_dict().items(), tiny_model(cfg).state_dict().values(), strict=True):
        assert torch.equal(got, want), name
