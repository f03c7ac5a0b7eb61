"""``scripts/train_bundled_depth.py``: the loss sees what inference gives, and the loss is scale-and-shift invariant."""

from __future__ import annotations

import torch
from fixtures_scripts import load_script

from depthnerf.depth.backend import PriorProvenance
from depthnerf.depth.bundled import BundledDepthNet, BundledEstimator, BundledNetConfig

train_bundled_depth = load_script("train_bundled_depth")


def _net(input_size: int) -> BundledDepthNet:
    torch.manual_seed(0)
    return BundledDepthNet(BundledNetConfig(widths=(4, 6, 8), input_size=input_size)).eval()


def test_training_prediction_is_the_estimators_prediction() -> None:
    """64 px images through a 128 px network: the trainer and the estimator share ``predict_at_image_size``."""
    net = _net(128)
    images = torch.rand(2, 3, 64, 64)
    estimator = BundledEstimator(net, PriorProvenance("bundled", None, "0" * 64, 128, "MIT"), "cpu")
    with torch.no_grad():
        trained = train_bundled_depth.predict_at_image_size(net, images)
    assert trained.shape == (2, 64, 64)
    torch.testing.assert_close(trained, estimator.predict(images), rtol=1e-5, atol=1e-6)


def test_images_at_the_network_size_go_straight_through() -> None:
    net = _net(64)
    images = torch.rand(1, 3, 64, 64)
    with torch.no_grad():
        torch.testing.assert_close(train_bundled_depth.predict_at_image_size(net, images), net(images))


def test_loss_is_invariant_to_scale_and_shift_of_the_prediction() -> None:
    torch.manual_seed(1)
    depth = 1.0 + torch.rand(2, 16, 16)
    depth[:, :3] = 0.0  # background rows
    pred = torch.rand(2, 16, 16)
    base = train_bundled_depth.ssi_loss(pred, depth)
    torch.testing.assert_close(train_bundled_depth.ssi_loss(3.0 * pred + 0.7, depth), base, rtol=1e-5, atol=1e-6)
    exact = torch.where(depth > 0, 1.0 / depth.clamp_min(1e-6), torch.zeros_like(depth))
    assert train_bundled_depth.ssi_loss(exact, depth) < 1e-5 < base
