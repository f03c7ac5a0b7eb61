"""The loss terms of one training step (``depthnerf.train.step.BatchLoss.losses``) from render outputs with
hand-computed colour errors, opacities and depth losses: which pass feeds which term, and the weights."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from depthnerf.render.config import RenderConfig
from depthnerf.train import step
from depthnerf.train.step import BatchLoss


class _FakeModel(torch.nn.Module):
    """Encodes nothing; its fields are markers handed to the (replaced) renderer."""

    def encode(self, source):
        return "encoded"

    def field(self, enc, which, runtime=None):
        return which


def _pass(rgb_error: tuple[float, float], opacity: list[list[float]]) -> SimpleNamespace:
    """Render output of 2 objects x 3 rays: colour ``0.5 + error`` of each object, the given opacities."""
    rgb = 0.5 + torch.tensor(rgb_error, dtype=torch.float64)[:, None, None].expand(2, 3, 3)
    distance = torch.rand(2, 3, dtype=torch.float64)
    return SimpleNamespace(rgb=rgb, opacity=torch.tensor(opacity, dtype=torch.float64, requires_grad=True),
                           normalized_distance=lambda: distance)


@pytest.mark.parametrize(("background_weight", "foreground_weight"), [(0.5, 0.0), (0.0, 0.0), (0.0, 2.0), (0.5, 2.0)])
def test_loss_terms_from_known_render_outputs(monkeypatch, background_weight, foreground_weight):
    """Coarse colour errors 0.1 / -0.3 (object 0 / 1) give MSE (0.01 + 0.09) / 2 = 0.05, fine errors 0.2 / 0
    give 0.02. Background opacity (object 0's rays 1, 2 and object 1's ray 2 are background): coarse opacities
    0.5 1 0.2 / 0.3 0 0.9 give per object (1 + 0.04) / 2 and 0.81, fine ones 0.1 0.2 0.4 / 0.5 0.5 0.5 give
    (0.04 + 0.16) / 2 and 0.25; the term is the mean over objects of coarse + fine, (0.62 + 1.06) / 2 = 0.84.
    Foreground transparency (object 0's ray 0, object 1's rays 0, 1): coarse (0.5^2) = 0.25 and
    (0.7^2 + 1^2) / 2 = 0.745, fine 0.9^2 = 0.81 and (0.25 + 0.25) / 2 = 0.25; the term is (1.06 + 0.995) / 2 =
    1.0275. The depth loss (per object 0.3 and 0.5, on the fine pass's distances) is 0.4. Total = coarse + fine +
    0.25 x depth + w_b x background + w_f x foreground, each opacity term measured (and detached) when its weight
    is 0."""
    coarse = _pass((0.1, -0.3), [[0.5, 1.0, 0.2], [0.3, 0.0, 0.9]])
    fine = _pass((0.2, 0.0), [[0.1, 0.2, 0.4], [0.5, 0.5, 0.5]])
    batch = SimpleNamespace(source=None, ray_origins=torch.zeros(2, 3, 3), ray_dirs=torch.ones(2, 3, 3),
                            target_rgb=torch.full((2, 3, 3), 0.5, dtype=torch.float64),
                            target_prior=torch.rand(2, 3), target_cos=torch.rand(2, 3),
                            target_fg=torch.tensor([[True, False, False], [True, True, False]]))

    def render(coarse_fn, fine_fn, rays, cfg, *, train, draws):
        assert (coarse_fn, fine_fn, train) == ("coarse", "fine", True)
        return SimpleNamespace(coarse=coarse, fine=fine)

    def depth_loss(distance, prior, fg, *, dirs_cam_z, opacity, min_opacity):
        assert distance is fine.normalized_distance() and prior is batch.target_prior
        assert fg is batch.target_fg and dirs_cam_z is batch.target_cos
        assert opacity is fine.opacity and min_opacity == 0.3
        return torch.tensor([0.3, 0.5], dtype=torch.float64), torch.ones(2, dtype=torch.bool)

    monkeypatch.setattr(step, "render_rays", render)
    monkeypatch.setattr(step, "ssi_depth_loss_per_image", depth_loss)
    terms = BatchLoss(_FakeModel(), RenderConfig(), 0.25, background_weight, foreground_weight=foreground_weight,
                      depth_min_opacity=0.3).losses(batch, 0.8, 1.8, None)
    assert terms.coarse.item() == pytest.approx(0.05, abs=1e-12)
    assert terms.fine.item() == pytest.approx(0.02, abs=1e-12)
    assert terms.depth.item() == pytest.approx(0.4, abs=1e-12)
    assert terms.background.item() == pytest.approx(0.84, abs=1e-12)
    assert terms.foreground.item() == pytest.approx(1.0275, abs=1e-12)
    assert terms.total.item() == pytest.approx(
        0.05 + 0.02 + 0.25 * 0.4 + background_weight * 0.84 + foreground_weight * 1.0275, abs=1e-12)
    assert terms.background.requires_grad == (background_weight > 0)
    assert terms.foreground.requires_grad == (foreground_weight > 0)
