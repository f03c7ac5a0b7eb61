"""Per-object BatchNorm (``depthnerf.model.norm``) against normalisation written out channel by channel."""

from __future__ import annotations

import pytest
import torch

from depthnerf.model.norm import ObjectBatchNorm2d, object_groups


@pytest.mark.parametrize("views", [1, 2])
def test_image_statistics_normalise_each_object_with_its_own_moments(views):
    """An evaluation-mode layer under an ``image_stats`` plan: each object's samples (``views`` consecutive ones)
    normalised per channel with the mean and biased variance over its own samples and pixels, then the layer's
    own weight and bias for that channel; the running statistics are neither used nor changed."""
    gen = torch.Generator().manual_seed(3)
    objects, channels = 3, 4
    x = torch.randn(objects * views, channels, 5, 6, generator=gen, dtype=torch.float64) * 3 + 2
    bn = ObjectBatchNorm2d(channels, eps=0.05).double().eval()
    with torch.no_grad():
        bn.weight.copy_(torch.tensor([1.5, -0.5, 2.0, 0.25]))
        bn.bias.copy_(torch.tensor([0.1, -1.0, 0.0, 3.0]))
        bn.running_mean.fill_(5.0)
        bn.running_var.fill_(9.0)
    out = bn(x, object_groups(bn, objects, image_stats=True))
    expected = torch.empty_like(x)
    for k in range(objects):
        part = x[k * views:(k + 1) * views]
        for c in range(channels):
            values = part[:, c]
            mean = values.sum() / values.numel()
            var = ((values - mean) ** 2).sum() / values.numel()
            expected[k * views:(k + 1) * views, c] = ((values - mean) / torch.sqrt(var + 0.05) * bn.weight[c]
                                                      + bn.bias[c])
    torch.testing.assert_close(out, expected, rtol=1e-10, atol=1e-10)
    assert torch.equal(bn.running_mean, torch.full((channels,), 5.0, dtype=torch.float64))
    assert torch.equal(bn.running_var, torch.full((channels,), 9.0, dtype=torch.float64))
