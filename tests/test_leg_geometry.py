"""scripts/leg_geometry.py: the bottom-band scores against a brute-force loop, and legs told from a blob."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from fixtures_scripts import load_script

from depthnerf.eval.geometry_metrics import sample_surface


def _load():
    return load_script("leg_geometry")


def _brute_force(pred: np.ndarray, gt: np.ndarray, lo: np.ndarray, hi: np.ndarray, up: int, band: float,
                 tau: float) -> tuple[float, float]:
    diagonal = float(np.sqrt(((hi - lo) ** 2).sum()))
    cut = lo[up] + band * (hi[up] - lo[up])

    def near(p, others):
        return any(float(np.sqrt(((p - q) ** 2).sum())) / diagonal < tau for q in others)

    gt_band = [p for p in gt if p[up] < cut]
    pred_band = [p for p in pred if p[up] < cut]
    recall = sum(near(p, pred) for p in gt_band) / len(gt_band)
    precision = sum(near(p, gt) for p in pred_band) / len(pred_band) if pred_band else 0.0
    return precision, recall


@pytest.mark.parametrize("up", [1, 2])
def test_band_scores_equal_a_brute_force_loop(up: int) -> None:
    lg = _load()
    rng = np.random.default_rng(up)
    lo, hi = np.array([-0.3, -0.4, -0.5]), np.array([0.3, 0.4, 0.5])
    gt = rng.uniform(lo, hi, size=(300, 3))
    pred = np.concatenate([gt[:120] + rng.normal(0, 0.01, (120, 3)), rng.uniform(lo, hi, size=(80, 3))])
    got = lg.band_scores(pred, gt, lo, hi, up, band=0.35, tau=0.03)
    precision, recall = _brute_force(pred, gt, lo, hi, up, 0.35, 0.03)
    assert got["band_precision"] == pytest.approx(precision, abs=1e-12)
    assert got["band_recall"] == pytest.approx(recall, abs=1e-12)
    assert got["band_fscore"] == pytest.approx(2 * precision * recall / (precision + recall), abs=1e-12)
    assert 0.0 < recall < 1.0 and 0.0 < precision < 1.0


def test_distances_reach_across_the_cut_and_an_empty_prediction_scores_zero() -> None:
    lg = _load()
    lo, hi = np.zeros(3), np.array([1.0, 1.0, 1.0])
    gt = np.array([[0.5, 0.5, 0.340], [0.5, 0.5, 0.9]])        # one point in the band (cut at z = 0.35)
    pred = np.array([[0.5, 0.5, 0.355], [0.5, 0.5, 0.9]])      # its only match sits just above the cut
    got = lg.band_scores(pred, gt, lo, hi, up=2, band=0.35, tau=0.02)
    assert got["band_recall"] == 1.0           # the leg point is found by a point above the cut
    assert got["band_precision"] == 0.0        # the prediction has no surface in the band
    assert lg.band_scores(np.zeros((0, 3)), gt, lo, hi, 2, 0.35, 0.02) == {
        "band_precision": 0.0, "band_recall": 0.0, "band_fscore": 0.0}
    with pytest.raises(ValueError, match="no ground-truth point"):
        lg.band_scores(pred, gt[1:], lo, hi, 2, 0.35, 0.02)


def _chair(leg: float) -> trimesh.Trimesh:
    """A seat slab on four square legs of side ``leg`` (z up, 1 high)."""
    parts = [trimesh.creation.box(extents=(0.5, 0.5, 0.05),
                                  transform=trimesh.transformations.translation_matrix((0, 0, 0.45)))]
    for x in (-0.22, 0.22):
        for y in (-0.22, 0.22):
            parts.append(trimesh.creation.box(extents=(leg, leg, 0.45),
                                              transform=trimesh.transformations.translation_matrix((x, y, 0.225))))
    parts.append(trimesh.creation.box(extents=(0.5, 0.04, 0.55),
                                      transform=trimesh.transformations.translation_matrix((0, 0.23, 0.75))))
    return trimesh.util.concatenate(parts)


def test_legs_score_higher_than_a_blob_that_fills_the_space_between_them() -> None:
    lg = _load()
    gt_mesh = _chair(0.04)
    lo, hi = np.asarray(gt_mesh.bounds[0]), np.asarray(gt_mesh.bounds[1])
    gt = sample_surface(gt_mesh, 20_000, 0)
    blob = trimesh.creation.box(extents=(0.5, 0.5, 0.45),
                                transform=trimesh.transformations.translation_matrix((0, 0, 0.225)))
    legs = lg.band_scores(sample_surface(_chair(0.045), 20_000, 0), gt, lo, hi, 2, 0.35, 0.01)
    filled = lg.band_scores(sample_surface(trimesh.util.concatenate([_chair(0.04), blob]), 20_000, 0), gt, lo, hi,
                            2, 0.35, 0.01)
    assert legs["band_fscore"] > 0.8
    assert filled["band_precision"] < 0.5 < legs["band_precision"]


def test_paired_counts_no_worse_objects() -> None:
    lg = _load()
    base = {"a": {"band_precision": 0.2, "band_recall": 0.5, "band_fscore": 0.3},
            "b": {"band_precision": 0.4, "band_recall": 0.5, "band_fscore": 0.4},
            "c": {"band_precision": 0.4, "band_recall": 0.5, "band_fscore": 0.4}}
    method = {"a": {"band_precision": 0.3, "band_recall": 0.5, "band_fscore": 0.4},
              "b": {"band_precision": 0.3, "band_recall": 0.6, "band_fscore": 0.4},
              "d": {"band_precision": 0.9, "band_recall": 0.9, "band_fscore": 0.9}}   # d: not in the baseline
    rows = {r["metric"]: r for r in lg.paired(base, method)}
    assert rows["band_precision"]["objects"] == 2 and rows["band_precision"]["no_worse"] == 1
    assert rows["band_precision"]["diff"] == pytest.approx(0.0)
    assert rows["band_recall"]["no_worse"] == 2 and rows["band_fscore"]["diff"] == pytest.approx(0.05)
