"""Camera placements of the SRN protocol: random upper-hemisphere views (train) and the Archimedean spiral (val/test).

All cameras look at the origin from a fixed radius with world +z up (see :mod:`depthnerf.data.cameras`), with
poses from :func:`~depthnerf.data.cameras.look_at`. Elevation is capped at ``max_elevation_deg`` (< 90) because
``look_at`` is undefined at the pole.

Train views: uniform in *area* on the upper hemisphere: ``z = r * u`` with ``u ~ U(0, sin(max_elevation))`` and
azimuth ``~ U(0, 2 pi)`` (Archimedes' hat-box theorem: ``z`` uniform means area-uniform on a sphere zone).

Val/test views: SRN's spiral: elevation rises linearly with the view index from 0 (horizon) to the cap while the
azimuth advances by a constant step (SRN: 20 rad over the whole spiral, ~3.2 turns), so elevation is monotone and
all views lie on the sphere. The azimuth is offset so that view ``input_view`` (SRN's standard input view 64) is
at ``input_azimuth_deg`` from the object's front (+x), a side-ish view at low elevation, as in SRN.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from depthnerf.data.cameras import look_at


@dataclass(frozen=True)
class ViewConfig:
    """Where the cameras are."""

    radius: float = 1.3
    """Camera distance from the origin (SRN: 1.3 for cars, 2.0 for chairs)."""
    max_elevation_deg: float = 89.0
    """Elevation cap below the pole."""
    spiral_azimuth_span: float = 20.0
    """Total azimuth travelled by the spiral, radians (SRN: 20)."""
    input_view: int = 64
    """The standard input view of a test object."""
    input_azimuth_deg: float = 65.0
    """Azimuth of the standard input view, degrees from the object's front (+x) towards its left (+y)."""


def eyes_from_angles(radius: float, elevation: np.ndarray, azimuth: np.ndarray) -> np.ndarray:
    """Camera centres (``N x 3``) on a sphere from elevation/azimuth in radians."""
    return radius * np.stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                              np.sin(elevation)], axis=1)


def hemisphere_eyes(n: int, cfg: ViewConfig, rng: np.random.Generator) -> np.ndarray:
    """``n`` camera centres uniform in area on the upper hemisphere (below the elevation cap)."""
    u = rng.uniform(0.0, math.sin(math.radians(cfg.max_elevation_deg)), size=n)
    azimuth = rng.uniform(0.0, 2 * math.pi, size=n)
    return eyes_from_angles(cfg.radius, np.arcsin(u), azimuth)


def spiral_eyes(n: int, cfg: ViewConfig) -> np.ndarray:
    """``n`` camera centres on the Archimedean spiral from the horizon up to the elevation cap."""
    s = np.arange(n) / max(n - 1, 1)
    elevation = np.radians(cfg.max_elevation_deg) * s
    step = cfg.spiral_azimuth_span / max(n - 1, 1)
    anchor = min(cfg.input_view, n - 1)
    azimuth = math.radians(cfg.input_azimuth_deg) + step * (np.arange(n) - anchor)
    return eyes_from_angles(cfg.radius, elevation, azimuth)


def poses_from_eyes(eyes: np.ndarray) -> np.ndarray:
    """Camera-to-world poses (``N x 4 x 4`` float32, OpenCV axes) looking at the origin with +z up."""
    return look_at(torch.as_tensor(eyes, dtype=torch.float32)).numpy()
