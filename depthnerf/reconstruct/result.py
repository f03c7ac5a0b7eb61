"""What a reconstruction produces (:class:`Reconstruction`), written by :mod:`depthnerf.reconstruct.exports`."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import trimesh
from jaxtyping import Float

from depthnerf.data.cameras import Intrinsics
from depthnerf.reconstruct.photo import PreparedImage


@dataclass
class Reconstruction:
    """Everything reconstructed from one photo (arrays on the CPU)."""

    input: PreparedImage
    """The prepared input view."""
    depth_prior: Float[np.ndarray, "H W"] | None
    """Raw relative disparity from the estimator (None for the baseline)."""
    prior_normalized: Float[np.ndarray, "H W"] | None
    """What the encoder saw: normalised disparity (foreground [-4, 4], background -5)."""
    poses: Float[np.ndarray, "N 4 4"]
    """Camera-to-world poses of the orbit views (OpenCV axes); pose 0 is the input camera."""
    intrinsics: Intrinsics
    """Intrinsics of the rendered views."""
    views: Float[np.ndarray, "N H W 3"]
    """Rendered RGB in [0, 1]."""
    depths: Float[np.ndarray, "N H W"]
    """Rendered ray distance of the visible surface (``far`` where nothing was hit)."""
    opacity: Float[np.ndarray, "N H W"]
    """Rendered opacity."""
    mesh: trimesh.Trimesh
    """World-frame mesh with vertex colours (empty when the density never reached the level or meshing was off)."""
    points: Float[np.ndarray, "P 3"]
    """World-frame point cloud."""
    point_colors: Float[np.ndarray, "P 3"]
    """Point colours in [0, 1]."""
    settings: dict[str, Any]
    """Camera, framing, depth prior and mesh settings actually used."""
    timings: dict[str, float] = field(default_factory=dict)
    """Seconds per stage."""
