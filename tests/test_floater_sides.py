"""scripts/floater_sides.py: side labels against hand-placed points, and the split adds up to the floater fraction."""

from __future__ import annotations

import numpy as np
import trimesh
from fixtures_scripts import load_script

from depthnerf.eval.geometry_metrics import GeometryConfig, floater_fraction, outside_box


def _load():
    return load_script("floater_sides")


def test_hand_placed_points_get_their_side() -> None:
    fs = _load()
    lo, hi = np.array([-1.0, -0.5, 0.0]), np.array([1.0, 0.5, 0.6])
    camera = np.array([0.3, -4.0, 1.5])          # -y side, above: near = the face at y = -0.5
    points = np.array([
        [0.0, -0.9, 0.3],    # in front of the near face
        [0.0, 0.9, 0.3],     # behind the far face
        [0.0, 0.0, 1.0],     # above
        [0.0, 0.0, -0.4],    # below
        [1.5, 0.0, 0.3],     # beyond +x
        [-1.5, 0.0, 0.3],    # beyond -x
        [0.0, 0.0, 0.3],     # inside
        [0.0, -0.55, 0.3],   # inside the grown box (margin 0.1)
        [0.0, -0.7, 1.0],    # outside on y by 0.1 and on z by 0.3: z wins -> above
    ])
    labels = fs.classify_outside(points, lo, hi, 0.1, up=2, camera=camera)
    names = [fs.SIDES[k] if k >= 0 else "inside" for k in labels]
    assert names == ["near", "far", "above", "below", "lateral", "lateral", "inside", "inside", "above"]


def test_near_follows_the_camera_and_the_up_axis() -> None:
    fs = _load()
    lo, hi = -np.ones(3), np.ones(3)
    point = np.array([[1.5, 0.0, 0.0]])            # beyond +x
    # camera on +x: that face is near; camera on -x: far; up = x: above
    assert fs.SIDES[fs.classify_outside(point, lo, hi, 0.0, up=2, camera=np.array([5.0, 1.0, 3.0]))[0]] == "near"
    assert fs.SIDES[fs.classify_outside(point, lo, hi, 0.0, up=2, camera=np.array([-5.0, 1.0, 3.0]))[0]] == "far"
    assert fs.SIDES[fs.classify_outside(point, lo, hi, 0.0, up=0, camera=np.array([-5.0, 1.0, 3.0]))[0]] == "above"


def test_sides_add_up_to_the_floater_fraction() -> None:
    fs = _load()
    rng = np.random.default_rng(0)
    points = rng.uniform(-2.0, 2.0, size=(5000, 3))
    lo, hi = np.array([-1.0, -0.5, 0.0]), np.array([1.0, 0.5, 0.6])
    labels = fs.classify_outside(points, lo, hi, 0.05, up=2, camera=np.array([0.0, -3.0, 1.0]))
    assert np.array_equal(labels >= 0, outside_box(points, lo, hi, 0.05))
    # on meshes, with the eval's samples: the five fractions sum to geometry_metrics.floater_fraction
    gt = trimesh.creation.box(extents=(2.0, 1.0, 0.6))
    slab = trimesh.creation.box(extents=(2.0, 0.2, 0.6),
                                transform=trimesh.transformations.translation_matrix((0.0, -1.0, 0.0)))
    pred = trimesh.util.concatenate([gt, slab])
    config = GeometryConfig(n_points=4000)
    sides = fs.side_fractions(pred, gt, np.array([0.0, -3.0, 1.0]), up=2, config=config)
    assert abs(sum(sides.values()) - floater_fraction(pred, gt, config)) < 1e-12
    assert sides["near"] > 0.1 and sides["far"] == 0.0 and sides["above"] == 0.0
