"""scripts/colour_fidelity.py's per-view measure against CIELAB values worked out by hand."""

from __future__ import annotations

import numpy as np
import pytest
from fixtures_scripts import load_script


def _load():
    return load_script("colour_fidelity")  # it imports angle_bins from beside it


def test_grey_render_of_a_coloured_object_loses_all_its_chroma():
    colour = _load()
    gt = np.full((8, 8, 3), 255, np.uint8)
    gt[2:6, 2:6] = (200, 40, 40)  # a red square on white
    grey = np.full((8, 8, 3), 255, np.uint8)
    grey[2:6, 2:6] = (90, 90, 90)
    same = colour.view_colour(gt, gt, white=0.95)
    assert same[0] == pytest.approx(same[1]) and same[2] == pytest.approx(0.0, abs=1e-9)
    chroma, gt_chroma, delta_ab = colour.view_colour(grey, gt, white=0.95)
    assert chroma == pytest.approx(0.0, abs=1e-2)  # neutral grey: a = b = 0 (to the matrices' rounding, ~2e-3)
    assert delta_ab == pytest.approx(gt_chroma, rel=1e-3)  # the distance from (0, 0) is the ground truth's chroma
    assert gt_chroma > 50  # a saturated red (CIELAB chroma of sRGB (200, 40, 40) is about 70)
    # only the ground truth's object pixels count: a white render there is as grey as the grey one
    white_render = np.full((8, 8, 3), 255, np.uint8)
    assert colour.view_colour(white_render, gt, white=0.95)[0] == pytest.approx(0.0, abs=1e-2)
    assert colour.view_colour(grey, np.full((8, 8, 3), 255, np.uint8), white=0.95) is None  # no object
