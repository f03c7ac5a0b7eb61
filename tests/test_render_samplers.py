"""Samplers: bins, determinism, inverse-CDF histograms against the pdf, Gaussian moments."""

import math
import statistics

import pytest
import torch

from depthnerf.render.samplers import (
    gap_bins,
    gaussian_samples,
    sample_pdf,
    stratified_samples,
    uniform_bin_edges,
)


def _bounds(r=6):
    near = torch.linspace(0.5, 1.0, r)[None]
    return near, near + torch.linspace(1.0, 2.0, r)[None]


def test_stratified_one_sample_per_bin_and_deterministic_at_eval():
    near, far = _bounds()
    n = 64
    edges = uniform_bin_edges(near, far, n)
    for random in (True, False):
        t = stratified_samples(near, far, n, random=random, generator=torch.Generator().manual_seed(3))
        assert t.shape == (1, 6, n)
        assert torch.all(t >= edges[..., :-1] - 1e-6) and torch.all(t <= edges[..., 1:] + 1e-6)
    a = stratified_samples(near, far, n, random=False)
    b = stratified_samples(near, far, n, random=False)
    assert torch.equal(a, b)
    assert torch.allclose(a, 0.5 * (edges[..., :-1] + edges[..., 1:]), atol=1e-6)  # midpoints
    r1 = stratified_samples(near, far, n, random=True, generator=torch.Generator().manual_seed(5))
    r2 = stratified_samples(near, far, n, random=True, generator=torch.Generator().manual_seed(5))
    r3 = stratified_samples(near, far, n, random=True, generator=torch.Generator().manual_seed(6))
    assert torch.equal(r1, r2) and not torch.equal(r1, r3)
    # jitter is uniform within the bin: fractional positions over many rays have mean 1/2, variance 1/12
    near_big, far_big = torch.zeros(1, 4000), torch.ones(1, 4000)
    frac = stratified_samples(near_big, far_big, 8, random=True, generator=torch.Generator().manual_seed(0)) * 8
    frac = frac - torch.arange(8)
    assert abs(frac.mean().item() - 0.5) < 0.01 and abs(frac.var().item() - 1 / 12) < 0.005


def test_importance_samples_concentrate_on_delta_weights():
    near, far = torch.zeros(1, 100), torch.ones(1, 100)
    k, n_bins = 37, 64
    weights = torch.zeros(1, 100, n_bins)
    weights[..., k] = 1.0
    edges = uniform_bin_edges(near, far, n_bins)
    for random in (True, False):
        t = sample_pdf(edges, weights, 16, random=random, generator=torch.Generator().manual_seed(0))
        inside = (t >= k / n_bins) & (t <= (k + 1) / n_bins)
        assert inside.float().mean() > 0.9


def test_importance_histogram_matches_pdf():
    g = torch.Generator().manual_seed(1)
    n_bins, n = 10, 200_000
    weights = torch.rand(1, 1, n_bins, generator=g) ** 2
    edges = torch.sort(torch.rand(1, 1, n_bins + 1, generator=g), dim=-1).values * 2 + 1
    t = sample_pdf(edges, weights, n, random=True, generator=g, epsilon=0.0)
    pdf = (weights / weights.sum())[0, 0]
    idx = torch.searchsorted(edges[0, 0].contiguous(), t[0, 0].contiguous(), right=True) - 1
    freq = torch.bincount(idx.clamp(0, n_bins - 1), minlength=n_bins).double() / n
    tol = 5 * torch.sqrt(pdf * (1 - pdf) / n) + 1e-4
    assert torch.all((freq - pdf).abs() < tol), (freq, pdf)
    # uniform inside a bin: positions within the heaviest bin have the uniform mean and variance
    kb = int(pdf.argmax())
    lo, hi = edges[0, 0, kb], edges[0, 0, kb + 1]
    u = (t[0, 0][idx == kb] - lo) / (hi - lo)
    assert abs(u.mean().item() - 0.5) < 0.01 and abs(u.var().item() - 1 / 12) < 0.005


def test_importance_eval_is_deterministic_quantiles_and_skips_zero_width_bins():
    edges = torch.tensor([[[0.0, 1.0, 1.0, 2.0]]])
    weights = torch.tensor([[[1.0, 5.0, 1.0]]])  # the heavy bin has zero width
    t = sample_pdf(edges, weights, 4, random=False, epsilon=0.0)
    assert torch.equal(t, sample_pdf(edges, weights, 4, random=False, epsilon=0.0))
    assert torch.allclose(t, torch.tensor([[[0.25, 0.75, 1.25, 1.75]]]))  # quantiles of the 2 unit bins


def test_gaussian_samples_moments_and_clamp():
    n = 100_000
    center = torch.tensor([[1.3, 0.805]])
    near, far = torch.full((1, 2), 0.8), torch.full((1, 2), 1.8)
    t = gaussian_samples(center, near, far, n, 0.01, random=True, generator=torch.Generator().manual_seed(0))
    free = t[0, 0]
    assert abs(free.mean().item() - 1.3) < 4 * 0.01 / math.sqrt(n)
    assert abs(free.std().item() - 0.01) < 0.01 * 0.02
    assert t[0, 1].min() >= 0.8 and (t[0, 1] == 0.8).float().mean() > 0.2  # clamped to near
    det = gaussian_samples(center, near, far, 16, 0.01, random=False)
    assert torch.equal(det, gaussian_samples(center, near, far, 16, 0.01, random=False))
    assert abs(det[0, 0].mean().item() - 1.3) < 1e-6
    assert 0.008 < det[0, 0].std().item() < 0.0105  # normal quantiles: std a little under sigma


def test_gaussian_samples_are_differentiable_in_center():
    center = torch.tensor([[1.2]], requires_grad=True)
    t = gaussian_samples(center, torch.full((1, 1), 0.8), torch.full((1, 1), 1.8), 8, 0.01, random=False)
    t.sum().backward()
    assert center.grad.item() == pytest.approx(8.0)


def test_gap_bins_max_filter():
    t = torch.tensor([[[1.0, 2.0, 3.0]]])
    w = torch.tensor([[[0.1, 0.7, 0.2]]])
    edges, masses = gap_bins(t, w, torch.tensor([[0.5]]), torch.tensor([[4.0]]))
    assert torch.equal(edges, torch.tensor([[[0.5, 1.0, 2.0, 3.0, 4.0]]]))
    assert torch.allclose(masses, torch.tensor([[[0.1, 0.7, 0.7, 0.2]]]))


def test_importance_epsilon_goes_to_bins_of_positive_width_only():
    """Masses (w + eps) on the two unit bins, none on the zero-width one: [0, 1] gets (1 + 1) / 6 = 1/3,
    [1, 2] gets (3 + 1) / 6 = 2/3, and the quantiles (j + 0.5) / 4 invert that piecewise-linear CDF."""
    edges = torch.tensor([[[0.0, 1.0, 1.0, 2.0]]], dtype=torch.float64)
    weights = torch.tensor([[[1.0, 5.0, 3.0]]], dtype=torch.float64)
    t = sample_pdf(edges, weights, 4, random=False, epsilon=1.0)
    expect = []
    for j in range(4):
        u = (j + 0.5) / 4
        expect.append(u / (1 / 3) if u < 1 / 3 else 1.0 + (u - 1 / 3) / (2 / 3))
    assert torch.allclose(t, torch.tensor([[expect]], dtype=torch.float64), atol=1e-12)



def test_importance_on_a_ray_without_mass_spreads_over_its_positive_width_bins():
    """All weights 0 and ``epsilon = 0``: equal mass on the three positive-width bins of [0, 3] (the zero-width
    one gets none), so the quantiles (j + 0.5) / 6 land at 3 (j + 0.5) / 6, not all at the far edge; a ray with
    mass beside it is sampled as before."""
    edges = torch.tensor([[0.0, 1.0, 1.0, 2.0, 3.0], [0.0, 1.0, 1.0, 2.0, 3.0]], dtype=torch.float64)
    weights = torch.tensor([[0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]], dtype=torch.float64)
    t = sample_pdf(edges, weights, 6, random=False, epsilon=0.0)
    assert torch.allclose(t[0], torch.tensor([3 * (j + 0.5) / 6 for j in range(6)], dtype=torch.float64),
                          atol=1e-12)
    assert torch.allclose(t[1], torch.tensor([1 + (j + 0.5) / 6 for j in range(6)], dtype=torch.float64),
                          atol=1e-12)
    g = torch.Generator().manual_seed(0)
    drawn = sample_pdf(edges[:1], weights[:1], 4000, random=True, generator=g, epsilon=0.0)
    assert drawn.min() >= 0 and drawn.max() <= 3 and abs(drawn.mean().item() - 1.5) < 0.05


def test_importance_samples_match_a_loop_that_inverts_the_cdf_bin_by_bin():
    """Given variates ``u``: walk the bins in order, accumulating mass ``(w_k + eps) / sum`` over positive-width
    bins, and place ``u`` in the first bin whose cumulative mass exceeds it, linearly inside it."""
    g = torch.Generator().manual_seed(2)
    rays, n_bins, n, eps = 5, 9, 40, 0.05
    edges = torch.sort(torch.rand(rays, n_bins + 1, generator=g, dtype=torch.float64), dim=-1).values
    edges[:, 3] = edges[:, 4]  # one zero-width bin per ray
    weights = torch.rand(rays, n_bins, generator=g, dtype=torch.float64)
    u = torch.rand(rays, n, generator=g, dtype=torch.float64)
    t = sample_pdf(edges, weights, n, random=True, epsilon=eps, u=u)
    for r in range(rays):
        e = edges[r].tolist()
        mass = [(weights[r, k].item() + eps) if e[k + 1] > e[k] else 0.0 for k in range(n_bins)]
        total = sum(mass)
        for j in range(n):
            below = 0.0
            for k in range(n_bins):
                p = mass[k] / total
                if p > 0 and u[r, j].item() < below + p:
                    expect = e[k] + (u[r, j].item() - below) / p * (e[k + 1] - e[k])
                    break
                below += p
            assert abs(t[r, j].item() - expect) < 1e-12


def test_stratified_eval_offset_places_samples_at_that_fraction_of_each_bin():
    near, far = torch.tensor([[0.8, 1.0]]), torch.tensor([[1.8, 3.0]])
    t = stratified_samples(near, far, 8, random=False, eval_offset=0.25)
    for r in range(2):
        h = (far[0, r] - near[0, r]) / 8
        expect = torch.tensor([near[0, r] + (k + 0.25) * h for k in range(8)])
        assert torch.allclose(t[0, r], expect, atol=1e-6)


def test_gaussian_eval_samples_are_normal_quantiles():
    """Deterministic Gaussian samples are ``center + std * Phi^-1((k + 0.5) / n)`` (the standard library's
    inverse normal CDF as the reference)."""
    n, std = 16, 0.05
    center, near, far = (torch.tensor([[x]], dtype=torch.float64) for x in (1.3, 0.8, 1.8))
    t = gaussian_samples(center, near, far, n, std, random=False)
    normal = statistics.NormalDist()
    expect = torch.tensor([1.3 + std * normal.inv_cdf((k + 0.5) / n) for k in range(n)], dtype=torch.float64)
    assert torch.allclose(t[0, 0], expect, atol=1e-12)
