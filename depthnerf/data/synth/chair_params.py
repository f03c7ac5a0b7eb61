"""What a procedural chair is before it is meshed: its sampled structure, proportions and materials.

:class:`ChairParams` is drawn by :func:`depthnerf.data.synth.chairs.sample_chair` and read by the part builders of
:mod:`depthnerf.data.synth.chair_parts`; both import it from here (``chairs`` still exports it). Nominal units,
floor at z = 0, as in :mod:`depthnerf.data.synth.chairs`.
"""

from __future__ import annotations

from dataclasses import dataclass

from depthnerf.data.synth.primitives import Material


@dataclass
class ChairParams:
    """Sampled structure, proportions and materials of one chair (nominal units, floor at z = 0)."""

    archetype: str
    """One of :data:`~depthnerf.data.synth.chairs.CHAIR_ARCHETYPES` (or of ``HELDOUT_ARCHETYPES``)."""
    legs: str
    """``four``, ``swivel``, ``sled``, ``pedestal`` or ``panel``."""
    back: str
    """``solid``, ``curved``, ``slats``, ``ladder``, ``spindles``, ``splat``, ``office``, ``shell`` or ``none``."""
    arms: str
    """``none``, ``posts``, ``office``, ``tube``, ``panel`` or ``shell``."""
    seat_shape: str
    """``rect``, ``rounded``, ``trapezoid`` or ``round``."""
    dims: dict[str, float]
    """Proportions: seat_h (top of seat), seat_w, seat_d, seat_t, back_h (above seat), back_tilt (rad), leg_t,
    splay, back_curve, arm_h (above seat), cushion_t, panel_t."""
    options: dict[str, int]
    """Discrete options: n_slats, round_legs, tapered, stretchers (0 none, 1 H, 2 box, 3 ring), seat_cushion,
    back_cushion, cantilever (sled), headrest (office), star_phase (degrees, swivel base)."""
    frame: Material
    """Legs, posts, rails."""
    seat: Material
    """Seat and solid back panel."""
    cushion: Material
    """Cushions and upholstery."""
    finish: str
    """Names of the frame/seat/cushion finishes, for the dataset card."""
