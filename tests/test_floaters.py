"""The floater fraction of eval summaries, against a brute-force count and a closed form."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from depthnerf.eval.geometry_metrics import (
    GeometryConfig,
    floater_fraction,
    geometry_metrics,
    sample_surface,
    summarize_geometry,
)


def _box(extents, center) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=extents, transform=trimesh.transformations.translation_matrix(center))


def test_floater_fraction_equals_a_brute_force_count() -> None:
    gt = _box((1.0, 0.5, 0.4), (0.0, 0.0, 0.0))
    pred = trimesh.util.concatenate([_box((0.9, 0.45, 0.35), (0.02, 0.0, 0.0)),
                                     _box((0.6, 0.6, 0.05), (0.1, 0.05, 0.5))])  # a slab above the object
    cfg = GeometryConfig(n_points=4000, seed=3, floater_margin=0.05)
    points = sample_surface(pred, cfg.n_points, cfg.seed)
    lo, hi = gt.bounds
    margin = 0.05 * float(np.sqrt(1.0 ** 2 + 0.5 ** 2 + 0.4 ** 2))
    outside = 0
    for p in points:
        inside = all(lo[a] - margin <= p[a] <= hi[a] + margin for a in range(3))
        outside += 0 if inside else 1
    assert floater_fraction(pred, gt, cfg) == outside / len(points)
    assert 0.1 < outside / len(points) < 0.9


def test_floater_fraction_closed_form_and_in_metrics() -> None:
    gt = _box((1.0, 1.0, 1.0), (0.0, 0.0, 0.0))
    slab = _box((1.0, 1.0, 0.1), (0.0, 0.0, 2.0))  # entirely outside, also with the margin
    pred = trimesh.util.concatenate([gt, slab])
    expected = slab.area / (gt.area + slab.area)
    cfg = GeometryConfig(n_points=100_000)
    got = floater_fraction(pred, gt, cfg)
    assert got == pytest.approx(expected, abs=0.005)
    metrics = geometry_metrics(pred, gt, cfg)
    assert metrics.floater_fraction == got
    assert geometry_metrics(gt, gt, cfg).floater_fraction == 0.0
    summary = summarize_geometry([metrics, geometry_metrics(gt, gt, cfg)], cfg)
    assert summary["floater_fraction"] == pytest.approx(got / 2)
    assert summary["floater_margin"] == cfg.floater_margin


def test_margin_and_empty_prediction() -> None:
    gt = _box((1.0, 1.0, 1.0), (0.0, 0.0, 0.0))
    near = _box((1.0, 1.0, 0.02), (0.0, 0.0, 0.52))  # within 0.05 diagonals (0.087) of the top face
    assert floater_fraction(near, gt, GeometryConfig(n_points=2000)) == 0.0
    assert floater_fraction(near, gt, GeometryConfig(n_points=2000, floater_margin=0.0)) > 0.9
    empty = trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    assert floater_fraction(empty, gt) == 0.0
    assert geometry_metrics(empty, gt).floater_fraction == 0.0


def test_margin_is_in_gt_diagonals_not_world_units() -> None:
    """GT box of side 4 (diagonal 4 sqrt(3) ~ 6.93): the default margin 0.05 diagonals is ~0.35 world units, so a
    slab 0.2 above the top face is not a floater and one 0.5 above is (all of its surface, in closed form)."""
    gt = _box((4.0, 4.0, 4.0), (0.0, 0.0, 0.0))
    cfg = GeometryConfig(n_points=2000)
    margin = 0.05 * 4.0 * np.sqrt(3.0)
    for gap, expected in ((0.2, 0.0), (0.5, 1.0)):
        assert (gap < margin) == (expected == 0.0)
        slab = _box((2.0, 2.0, 0.02), (0.0, 0.0, 2.0 + gap))
        assert floater_fraction(slab, gt, cfg) == expected


def test_surface_on_the_box_faces_is_inside_even_without_margin() -> None:
    """The grown box is closed: the GT's own surface (samples exactly on its bounding faces) has no floaters."""
    gt = _box((1.0, 0.5, 0.4), (0.1, 0.0, 0.0))
    assert floater_fraction(gt, gt, GeometryConfig(n_points=2000, floater_margin=0.0)) == 0.0
