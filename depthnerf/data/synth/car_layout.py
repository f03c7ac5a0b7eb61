"""What a procedural car is before it is meshed: its sampled parameters and the layout derived from them.

:class:`CarParams` (drawn by :func:`depthnerf.data.synth.cars.sample_car`) and :class:`CarLayout` (its x/z
landmarks, :func:`layout`) are shared by the body builders of :mod:`depthnerf.data.synth.cars` and the detail
builders of :mod:`depthnerf.data.synth.car_parts`; both import them from here (``cars`` still exports them).
Same frame and units as :mod:`depthnerf.data.synth.cars` (length 1 along +x, ground at z = 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from depthnerf.data.synth.primitives import Material


@dataclass
class CarParams:
    """Sampled shape and appearance of one car (lengths in units of the car length, ground at z = 0)."""

    style: str
    """One of :data:`~depthnerf.data.synth.cars.CAR_STYLES` (or of ``HELDOUT_CAR_STYLES``)."""
    dims: dict[str, float]
    """Sampled values of the style's ranges (see ``_STYLE_RANGES`` in :mod:`depthnerf.data.synth.cars`)."""
    paint: Material
    """Body paint."""
    paint_name: str
    """Name of the paint colour (for the dataset card)."""
    roof: str
    """Roof finish: ``paint``, ``contrast`` (black or white) or ``glass`` (panoramic)."""
    blackout_pillars: bool
    """Black window pillars instead of paint."""
    rim: str
    """Rim style: ``disc``, ``dish`` or ``spokes``."""
    rim_color: tuple[float, float, float]
    """Rim albedo."""
    cladding: bool
    """Dark plastic lower body trim (SUV/pickup look)."""
    spoiler: bool
    """Rear wing (sports cars)."""
    cargo: bool
    """Van without rear side windows."""


@dataclass
class CarLayout:
    """Derived x/z landmarks of a car (length units), shared by the body, glasshouse and detail builders."""

    p: CarParams
    """The parameters."""
    axles: tuple[float, float]
    """x of the front and rear axle."""
    screen_base: float
    """x where the windscreen meets the bonnet."""
    screen_top: float
    """x of the top of the windscreen."""
    roof_back: float
    """x where the roof ends (top of the rear window)."""
    glass_back: float
    """x of the bottom of the rear window / back of the cabin."""
    nose_radius: float
    """Rounding radius of the body ends."""

    def half_width(self, x: np.ndarray) -> np.ndarray:
        """Plan half-width of the lower body (tapers and rounds towards the ends)."""
        w = self.p.dims["width"] / 2
        front = np.clip((x - self.axles[0]) / (0.5 - self.axles[0]), 0, 1)
        rear = np.clip((self.axles[1] - x) / (self.axles[1] + 0.5), 0, 1)
        taper = 1 - 0.07 * front**2 - 0.05 * rear**2
        return w * taper - self._round(x)

    def _round(self, x: np.ndarray) -> np.ndarray:
        r = self.nose_radius
        s = np.clip((np.abs(x) - (0.5 - r)) / r, 0, 1)
        return r * (1 - np.sqrt(1 - s**2))

    def top(self, x: np.ndarray) -> np.ndarray:
        """Top line of the lower body: bonnet, belt and boot (or bed floor for pickups)."""
        d = self.p.dims
        belt = d["belt"]
        nose = belt - (0.04 if self.p.style != "van" else 0.05)
        front = np.clip((x - self.screen_base) / (0.5 - self.screen_base), 0, 1)
        z = belt + (nose - belt) * front**1.5
        if self.p.style == "pickup":
            z = np.where(x < self.glass_back, belt - 0.1, z)
        elif self.p.dims["rear_len"] > 0.06:  # boot or fastback tail slopes down slightly
            rear = np.clip((self.glass_back - x) / (self.glass_back + 0.5), 0, 1)
            z = z - 0.02 * rear**2
        return z - 0.6 * self._round(x)

    def bottom(self, x: np.ndarray) -> np.ndarray:
        """Bottom line of the lower body: the sill, raised over the wheel arches and at the rounded ends."""
        d = self.p.dims
        z = np.full_like(x, d["sill"]) + 0.5 * self._round(x)
        arch = 1.13 * d["wheel"]
        for ax in self.axles:
            inside = np.abs(x - ax) < arch
            z = np.where(inside, np.maximum(z, d["wheel"] + np.sqrt(np.clip(arch**2 - (x - ax) ** 2, 0, None))), z)
        return z


def layout(p: CarParams) -> CarLayout:
    """Place the axles and the glasshouse landmarks along x."""
    d = p.dims
    axles = (0.5 - d["front_oh"], -0.5 + d["rear_oh"])
    screen_base = 0.5 - d["hood"]
    screen_top = screen_base - d["screen"]
    roof_back = max(screen_top - d["roof_len"], -0.5 + d["rear_len"] + 0.01)
    glass_back = max(roof_back - d["rear_len"], -0.49)
    if p.style in ("hatchback", "wagon", "suv", "van", "microcar"):  # glasshouse runs to the tail
        glass_back = -0.5 + 0.012
        roof_back = glass_back + d["rear_len"]
    return CarLayout(p, axles, screen_base, screen_top, roof_back, glass_back, nose_radius=0.045)
