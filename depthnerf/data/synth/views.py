"""Camera placements of the SRN protocol: random upper-hemisphere views (train) and the Archimedean spiral (val/test).

Two framings (:mod:`depthnerf.data.synth.framing`): ``srn`` follows SRN's renderer (the ``srn_*`` functions
below, facts and sources in docs/data.md), ``legacy`` is generator ``depthnerf-synth-1``'s (:class:`ViewConfig` and
the functions that take one), kept bit-for-bit for the shipped checkpoints.

SRN framing
    Spiral (``vsitzmann/shapenet_renderer`` ``util.get_archimedean_spiral``): ``i`` runs from 20 to 40 rad in 250
    equal steps (251 views); polar angle ``i / 40 * pi`` from the horizon to the pole, azimuth ``-i`` in SRN's
    +y-up world. Mapped into depthnerf's +z-up world with SRN's ``(x, y, z)`` -> ``(-z, -x, y)`` (ShapeNetCore v2
    front -Z becomes +x, up +Y becomes +z) that is elevation ``90 deg * k / (n - 1)`` and azimuth
    ``i_k - pi / 2`` from +x towards +y. View 64: elevation 23.04 deg, azimuth 269.27 deg, the car's right side.
    Train views are area-uniform on the upper hemisphere up to the pole. Poses are built from the angles
    (:func:`poses_from_angles`), so the pole (the spiral's last view) has a defined roll.

Legacy framing
    All cameras look at the origin from a fixed radius with world +z up (see :mod:`depthnerf.data.cameras`),
    with poses from :func:`~depthnerf.data.cameras.look_at`. Elevation is capped at ``max_elevation_deg`` (< 90)
    because ``look_at`` is undefined at the pole. Train views: uniform in *area* on the upper hemisphere:
    ``z = r * u`` with ``u ~ U(0, sin(max_elevation))`` and azimuth ``~ U(0, 2 pi)`` (Archimedes' hat-box theorem:
    ``z`` uniform means area-uniform on a sphere zone). Val/test views: elevation rises linearly with the view
    index from 0 (horizon) to the cap while the azimuth advances by a constant step (20 rad over the spiral), offset
    so that view ``input_view`` (64) is at ``input_azimuth_deg`` (65 deg) from the object's front (+x): a
    three-quarter view, unlike SRN's side view.
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


SRN_SPIRAL_START = 20.0
"""SRN's spiral parameter ``i`` at view 0 (``a / 2`` with ``a = 40``), radians of (negative) azimuth."""
SRN_SPIRAL_SPAN = 20.0
"""Azimuth (radians) the SRN spiral turns from its first to its last view (``a / 2``)."""


def srn_spiral_angles(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Elevation and azimuth (radians, depthnerf's +z-up frame) of the ``n`` views of SRN's spiral."""
    s = np.arange(n) / max(n - 1, 1)
    i = SRN_SPIRAL_START + SRN_SPIRAL_SPAN * s
    return (math.pi / 2) * s, i - math.pi / 2


def srn_hemisphere_angles(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Elevation and azimuth (radians) of ``n`` views uniform in area on the whole upper hemisphere."""
    u = rng.uniform(0.0, 1.0, size=n)
    azimuth = rng.uniform(0.0, 2 * math.pi, size=n)
    return np.arcsin(u), azimuth


def poses_from_angles(radius: float, elevation: np.ndarray, azimuth: np.ndarray) -> np.ndarray:
    """Camera-to-world poses (``N x 4 x 4`` float32, OpenCV axes) on a sphere looking at the origin.

    The same cameras as :func:`~depthnerf.data.cameras.look_at` with +z up, but the image's right axis is taken
    from the azimuth, ``(-sin(az), cos(az), 0)`` (``look_at``'s right axis for every elevation below the pole),
    so a camera at the pole is defined too (its roll is the limit along its azimuth, as in SRN's renderer).
    """
    el, az = np.asarray(elevation, dtype=np.float64), np.asarray(azimuth, dtype=np.float64)
    eye = eyes_from_angles(radius, el, az)
    forward = -eye / radius
    right = np.stack([-np.sin(az), np.cos(az), np.zeros_like(az)], axis=1)
    down = np.cross(forward, right)
    c2w = np.zeros((len(eye), 4, 4))
    c2w[:, :3, 0], c2w[:, :3, 1], c2w[:, :3, 2], c2w[:, :3, 3] = right, down, forward, eye
    c2w[:, 3, 3] = 1.0
    return c2w.astype(np.float32)


def poses_from_eyes(eyes: np.ndarray) -> np.ndarray:
    """Camera-to-world poses (``N x 4 x 4`` float32, OpenCV axes) looking at the origin with +z up."""
    return look_at(torch.as_tensor(eyes, dtype=torch.float32)).numpy()
