"""The tensor-bundle base against brute force: every operation equals the same operation done field by field."""

from __future__ import annotations

from dataclasses import dataclass

import pytest
import torch
from torch import Tensor

from depthnerf.bundles import TensorBundle
from depthnerf.render.depth_guide import DepthGuide
from depthnerf.render.rays import RayBundle
from depthnerf.render.volume import RenderResult


@dataclass
class Inner(TensorBundle):
    a: Tensor
    b: Tensor | None


@dataclass
class Outer(TensorBundle):
    x: Tensor
    y: Tensor
    inner: Inner
    maybe: Tensor | None
    size: tuple[int, int]


def make(seed: int, b: int = 2, r: int = 5) -> Outer:
    g = torch.Generator().manual_seed(seed)
    return Outer(x=torch.randn(b, r, generator=g), y=torch.randn(b, r, 3, 2, generator=g),
                 inner=Inner(a=torch.randint(0, 9, (b, r, 4), generator=g), b=None), maybe=None, size=(7, 8))


def test_map_and_to_touch_every_tensor_and_nothing_else():
    o = make(0)
    m = o.map(lambda t: t * 2)
    assert torch.equal(m.x, o.x * 2) and torch.equal(m.y, o.y * 2) and torch.equal(m.inner.a, o.inner.a * 2)
    assert m.inner.b is None and m.maybe is None and m.size == (7, 8) and type(m) is Outer
    d = o.to(torch.float64)
    assert d.x.dtype == torch.float64 and d.inner.a.dtype == torch.float64 and d.size == (7, 8)


def test_slice_and_gather_against_loops():
    o = make(1)
    s = o.slice(1, 4)
    for name in ("x", "y"):
        assert torch.equal(getattr(s, name), getattr(o, name)[:, 1:4])
    assert torch.equal(s.inner.a, o.inner.a[:, 1:4])
    assert torch.equal(o.slice(3, 99).x, o.x[:, 3:])  # past the end: clipped like Python slicing
    assert torch.equal(o.slice(0, 1, dim=0).y, o.y[:1])
    idx = torch.tensor([[4, 0, 0], [2, 3, 1]])
    g = o.gather(idx)
    for row in range(2):
        for k in range(3):
            assert torch.equal(g.x[row, k], o.x[row, idx[row, k]])
            assert torch.equal(g.y[row, k], o.y[row, idx[row, k]])
            assert torch.equal(g.inner.a[row, k], o.inner.a[row, idx[row, k]])


def test_cat_against_per_field_cat():
    parts = [make(s, r=r) for s, r in ((2, 3), (3, 1), (4, 2))]
    c = Outer.cat(parts, dim=1)
    assert torch.equal(c.x, torch.cat([p.x for p in parts], 1)) and torch.equal(c.y, torch.cat([p.y for p in parts], 1))
    assert torch.equal(c.inner.a, torch.cat([p.inner.a for p in parts], 1)) and c.inner.b is None
    assert c.size == (7, 8) and c.maybe is None
    assert torch.equal(Outer.cat(parts[:1]).x, parts[0].x)
    with pytest.raises(ValueError):
        Outer.cat([])
    rebuilt = Outer.cat([c.slice(0, 3), c.slice(3, 4), c.slice(4, 6)], dim=1)
    assert torch.equal(rebuilt.y, c.y)


def test_render_bundles_use_the_base():
    g = torch.Generator().manual_seed(5)
    rays = RayBundle(*(torch.randn(2, 6, *s, generator=g) for s in ((3,), (3,), (), ())))
    assert torch.equal(rays.slice(2, 5).directions, rays.directions[:, 2:5])
    guide = DepthGuide(t_guess=torch.rand(2, 6), t_enter=torch.rand(2, 6), valid=torch.rand(2, 6) > 0.5,
                       occupied=torch.rand(2, 6) > 0.5, spread=torch.rand(2, 6))
    idx = torch.tensor([[5, 1], [0, 0]])
    picked = guide.gather(idx)
    assert torch.equal(picked.valid, torch.gather(guide.valid, 1, idx)) and picked.valid.dtype == torch.bool
    res = RenderResult(rgb=torch.rand(2, 6, 3), distance=torch.rand(2, 6), opacity=torch.rand(2, 6),
                       weights=torch.rand(2, 6, 4), t=torch.rand(2, 6, 4))
    both = RenderResult.cat([res.slice(0, 2), res.slice(2, 6)], dim=1)
    assert all(torch.equal(getattr(both, n), getattr(res, n)) for n in ("rgb", "distance", "opacity", "weights", "t"))
