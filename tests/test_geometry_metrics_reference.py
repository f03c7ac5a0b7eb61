"""Geometry metrics' summary and empty-prediction rules against hand-computed values."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from depthnerf.eval.geometry_metrics import (
    GeometryConfig,
    GeometryMetrics,
    floater_fraction,
    geometry_metrics,
    summarize_geometry,
)


def _metrics(chamfer: float, fscore: float, floaters: float, empty: bool = False) -> GeometryMetrics:
    return GeometryMetrics(chamfer_l1=chamfer, accuracy=2 * chamfer, completeness=0.0, precision=fscore,
                           recall=fscore, fscore=fscore, tau=0.01, scale=1.0, empty_prediction=empty,
                           floater_fraction=floaters)


def test_summary_is_the_plain_mean_over_objects():
    """Three objects with skewed values, so the mean differs from the median: (0.01 + 0.02 + 0.09) / 3 = 0.04."""
    results = [_metrics(0.01, 0.9, 0.0), _metrics(0.02, 0.6, 0.0), _metrics(0.09, 0.0, 0.6, empty=True)]
    summary = summarize_geometry(results)
    assert summary["chamfer_l1"] == pytest.approx(0.04) and summary["accuracy"] == pytest.approx(0.08)
    assert summary["fscore"] == pytest.approx(0.5) and summary["precision"] == pytest.approx(0.5)
    assert summary["floater_fraction"] == pytest.approx(0.2) and summary["completeness"] == 0.0
    assert summary["empty_predictions"] == 1 and summary["geometry_units"] == "ground-truth bounding-box diagonals"


def test_a_prediction_of_zero_area_is_an_empty_prediction():
    """Faces but no area (every triangle degenerate: collinear corners) score the worst-case values, no error."""
    gt = trimesh.creation.box(extents=(1.0, 2.0, 2.0))
    flat = trimesh.Trimesh(vertices=np.array([[0.0, 0, 0], [0.5, 0, 0], [1.0, 0, 0], [0.2, 0, 0]]),
                           faces=np.array([[0, 1, 2], [0, 3, 1]]), process=False)
    assert len(flat.faces) == 2 and flat.area == 0.0
    m = geometry_metrics(flat, gt, GeometryConfig(n_points=500))
    assert m.empty_prediction and (m.chamfer_l1, m.accuracy, m.completeness) == (1.0, 1.0, 1.0)
    assert (m.precision, m.recall, m.fscore, m.floater_fraction) == (0.0, 0.0, 0.0, 0.0)
    raw = geometry_metrics(flat, gt, GeometryConfig(n_points=500, normalize=False))
    assert raw.chamfer_l1 == pytest.approx(3.0)  # one GT diagonal, sqrt(1 + 4 + 4), in world units
    assert floater_fraction(flat, gt, GeometryConfig(n_points=500)) == 0.0
