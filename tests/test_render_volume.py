"""Compositing against closed forms and a brute-force per-ray loop."""

import math

import torch

from depthnerf.render.volume import composite, compute_deltas, render_weights


def _slab(t: torch.Tensor, s: float, t0: float, t1: float) -> torch.Tensor:
    return torch.where((t >= t0) & (t < t1), torch.full_like(t, s), torch.zeros_like(t))


def test_uniform_slab_matches_closed_form():
    """sigma = s on [t0, t1): T(t) = exp(-s clip(t - t0, 0, L)), opacity = 1 - exp(-s L),
    E[t] = t0 (1 - e^{-sL}) + 1/s - (L + 1/s) e^{-sL}."""
    near, far, s, t0, t1 = 0.5, 2.5, 3.0, 1.0, 1.75
    L = t1 - t0
    exact_depth = t0 * (1 - math.exp(-s * L)) + 1 / s - (L + 1 / s) * math.exp(-s * L)
    errors = []
    for n in (200, 800, 3200):  # grids with t0 and t1 on grid points: opacity/transmittance are exact
        t = torch.linspace(near, far, n + 1, dtype=torch.float64)[:-1][None, None]
        far_t = torch.full((1, 1), far, dtype=torch.float64)
        sigma = _slab(t, s, t0, t1)
        rgb = torch.zeros(*t.shape, 3, dtype=torch.float64)
        res = composite(t, far_t, sigma, rgb, white_background=False)
        _, trans = render_weights(sigma, compute_deltas(t, far_t))
        exact_trans = torch.exp(-s * (t - t0).clamp(0, L))
        assert torch.allclose(trans, exact_trans, atol=1e-12)
        assert abs(res.opacity.item() - (1 - math.exp(-s * L))) < 1e-12
        errors.append(abs(res.distance.item() - exact_depth))
        # depth uses the left end of each interval: first-order error bounded by one step
        assert errors[-1] <= (far - near) / n
    assert errors[1] < 0.3 * errors[0] and errors[2] < 0.3 * errors[1]  # converges linearly


def test_composite_matches_bruteforce_loop():
    g = torch.Generator().manual_seed(0)
    b, r, s = 2, 5, 17
    t = torch.sort(torch.rand(b, r, s, generator=g, dtype=torch.float64) * 2 + 1, dim=-1).values
    far = torch.full((b, r), 3.5, dtype=torch.float64)
    sigma = torch.randn(b, r, s, generator=g, dtype=torch.float64) * 3  # negative values are clamped (ReLU)
    rgb = torch.rand(b, r, s, 3, generator=g, dtype=torch.float64)
    res = composite(t, far, sigma, rgb, white_background=True)
    for bi in range(b):
        for ri in range(r):
            trans, color, depth, acc = 1.0, [0.0, 0.0, 0.0], 0.0, 0.0
            for i in range(s):
                delta = (t[bi, ri, i + 1] if i + 1 < s else far[bi, ri]) - t[bi, ri, i]
                alpha = 1 - math.exp(-max(sigma[bi, ri, i].item(), 0.0) * delta.item())
                w = alpha * trans
                assert abs(res.weights[bi, ri, i].item() - w) < 1e-12
                color = [c + w * rgb[bi, ri, i, k].item() for k, c in enumerate(color)]
                depth += w * t[bi, ri, i].item()
                acc += w
                trans *= 1 - alpha
            assert abs(res.opacity[bi, ri].item() - acc) < 1e-12
            assert abs(res.distance[bi, ri].item() - depth) < 1e-12
            for k in range(3):
                assert abs(res.rgb[bi, ri, k].item() - (color[k] + 1 - acc)) < 1e-12


def test_white_background_adds_one_minus_opacity():
    g = torch.Generator().manual_seed(1)
    t = torch.sort(torch.rand(1, 8, 12, generator=g), dim=-1).values
    far = torch.ones(1, 8) * 1.5
    sigma = torch.rand(1, 8, 12, generator=g) * 4
    rgb = torch.rand(1, 8, 12, 3, generator=g)
    black = composite(t, far, sigma, rgb, white_background=False)
    white = composite(t, far, sigma, rgb, white_background=True)
    assert torch.allclose(white.rgb - black.rgb, (1 - black.opacity)[..., None].expand(-1, -1, 3), atol=1e-6)
    assert (black.opacity > 0.05).all() and (black.opacity < 0.999).all()  # both terms matter here
    empty = composite(t, far, torch.zeros_like(sigma), rgb, white_background=True)
    assert torch.allclose(empty.rgb, torch.ones_like(empty.rgb)) and torch.all(empty.distance == 0)


def test_normalized_distance_is_the_weighted_mean_distance():
    """One absorbing sample at t_1 = 2 (optical depth tau, opacity 1 - e^-tau) behind an empty one:
    distance = (1 - e^-tau) * 2, and distance / opacity = 2 whatever the opacity."""
    t = torch.tensor([[[1.0, 2.0], [1.0, 2.0]]], dtype=torch.float64)
    far = torch.full((1, 2), 3.0, dtype=torch.float64)
    taus = (0.1, 5.0)  # optical depth of the last interval [2, far]: nearly transparent and nearly opaque
    sigma = torch.tensor([[[0.0, taus[0]], [0.0, taus[1]]]], dtype=torch.float64)
    res = composite(t, far, sigma, torch.zeros(1, 2, 2, 3, dtype=torch.float64), white_background=False)
    opacity = torch.tensor([[1 - math.exp(-tau) for tau in taus]], dtype=torch.float64)
    assert torch.allclose(res.opacity, opacity, atol=1e-12)
    assert torch.allclose(res.distance, 2.0 * opacity, atol=1e-12)
    assert torch.allclose(res.normalized_distance(), torch.full((1, 2), 2.0, dtype=torch.float64), atol=1e-12)
