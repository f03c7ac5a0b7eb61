"""Wheels and small details of the procedural cars (lamps, grille, bumpers, mirrors, pickup bed, spoiler).

Same frame and units as :mod:`depthnerf.data.synth.cars` (length 1 along +x, ground at z = 0). Details are small
solids half-sunk into the body so no seams show.
"""

from __future__ import annotations

import numpy as np

from depthnerf.data.synth.car_layout import CarLayout
from depthnerf.data.synth.primitives import (
    Material,
    MeshBuilder,
    beam,
    box,
    frame_from_axis,
    lathe,
    superellipsoid,
)

RUBBER = Material("rubber", (0.07, 0.07, 0.075), specular=0.05, shininess=10.0)
HEADLIGHT = Material("light", (0.96, 0.95, 0.88), specular=0.8, shininess=80.0, reflect=0.2, emission=0.55)
TAILLIGHT = Material("light", (0.78, 0.06, 0.05), specular=0.6, shininess=60.0, emission=0.35)
CHROME = Material("metal", (0.72, 0.73, 0.75), specular=0.9, shininess=90.0, reflect=0.5)


def _hw(lay: CarLayout, x: float) -> float:
    return float(lay.half_width(np.array([x]))[0])


def _top(lay: CarLayout, x: float) -> float:
    return float(lay.top(np.array([x]))[0])


def _bottom(lay: CarLayout, x: float) -> float:
    return float(lay.bottom(np.array([x]))[0])


def add_wheels(b: MeshBuilder, lay: CarLayout) -> None:
    """Four lathed tyres with rims of the car's rim style."""
    p = lay.p
    rw = p.dims["wheel"]
    tw = 0.05 + 0.25 * (rw - 0.064)
    rr = 0.64 * rw
    rim = Material("metal", p.rim_color, specular=0.8, shininess=70.0, reflect=0.3)
    dark = Material("metal", (0.14, 0.14, 0.15), specular=0.3, shininess=30.0)
    tyre_prof = [(0, -tw / 2), (0.86 * rw, -tw / 2), (0.97 * rw, -0.42 * tw), (rw, -0.26 * tw), (rw, 0.26 * tw),
                 (0.97 * rw, 0.42 * tw), (0.86 * rw, tw / 2), (0, tw / 2)]
    z0 = tw / 2
    disc_prof = [(0, z0 - 0.004), (rr, z0 - 0.004), (rr, z0 + 0.002), (0.8 * rr, z0 + 0.004), (0, z0 + 0.004)]
    hub_prof = [(0, z0), (0.3 * rr, z0), (0.3 * rr, z0 + 0.007), (0, z0 + 0.008)]
    for ax in lay.axles:
        for side in (1.0, -1.0):
            rot = frame_from_axis(np.array([0.0, side, 0.0]))
            centre = np.array([ax, side * (_hw(lay, ax) - tw / 2 - 0.006), rw])
            b.add(lathe(tyre_prof, 28).transformed(rot, centre), RUBBER)
            b.add(lathe(disc_prof, 24).transformed(rot, centre), dark if p.rim == "spokes" else rim)
            if p.rim in ("dish", "spokes"):
                b.add(lathe(hub_prof, 16).transformed(rot, centre), rim if p.rim == "spokes" else dark)
            if p.rim == "spokes":
                out = np.array([0.0, side, 0.0])
                face = centre + out * (z0 + 0.004)
                for k in range(5):
                    phi = 2 * np.pi * k / 5
                    radial = np.array([np.cos(phi), 0.0, np.sin(phi)])
                    b.add(beam(face + radial * 0.2 * rr, face + radial * 0.97 * rr, 0.16 * rr, 0.006, up=out), rim)


def add_details(b: MeshBuilder, lay: CarLayout, trim: Material) -> None:
    """Lamps, grille, bumpers, mirrors, and the style-specific pickup bed and spoiler."""
    p, d = lay.p, lay.p.dims
    w_front, w_rear = _hw(lay, 0.5), _hw(lay, -0.5)
    z_fl = _top(lay, 0.5) - 0.012
    for side in (1.0, -1.0):
        b.add(superellipsoid((0.02, 0.3 * w_front, 0.013), (0.5 - 0.011, side * 0.62 * w_front, z_fl),
                             e_vertical=0.5, e_horizontal=0.5, rows=8, cols=16), HEADLIGHT)
    front_h = z_fl - _bottom(lay, 0.5)
    if front_h > 0.04:
        b.add(superellipsoid((0.012, 0.3 * w_front, 0.35 * (front_h - 0.03)),
                             (0.5 - 0.006, 0.0, z_fl - 0.016 - 0.35 * (front_h - 0.03)), 0.3, 0.3, 8, 16), trim)
    if p.style == "pickup":
        z_tl = d["belt"] - 0.035
        x_tail = -0.5 + 0.006
    else:
        z_tl = _top(lay, -0.5) - 0.014
        x_tail = -0.5 + 0.01
    for side in (1.0, -1.0):
        b.add(superellipsoid((0.014, 0.16 * w_rear, 0.014), (x_tail, side * 0.72 * w_rear, z_tl),
                             0.4, 0.4, 8, 16), TAILLIGHT)
    bumper = p.paint if p.style in ("sedan", "hatchback", "wagon", "sports", "van") else (
        CHROME if p.style == "pickup" and p.rim == "disc" else trim)
    for x_end, w_end in ((0.5, w_front), (-0.5, w_rear)):
        z_b = _bottom(lay, x_end) + 0.006
        b.add(superellipsoid((0.022, 1.02 * w_end, 0.017), (np.sign(x_end) * (0.5 - 0.012), 0.0, z_b),
                             0.35, 0.35, 8, 24), bumper)
    x_m = lay.screen_base - 0.025
    for side in (1.0, -1.0):  # mirrors on the glasshouse side at the A-pillar foot (its inner end sunk into it)
        y_m = side * (0.9 * _hw(lay, x_m) + 0.012)
        b.add(superellipsoid((0.013, 0.02, 0.011), (x_m, y_m, _top(lay, x_m) + 0.016), 0.5, 0.5, 8, 12), p.paint)
    if p.style == "pickup":
        _add_bed(b, lay)
    if p.spoiler:
        x_s = -0.5 + 0.045
        z_s = _top(lay, x_s) + 0.035
        b.add(box((0.05, 1.7 * w_rear, 0.007), (x_s, 0.0, z_s)), p.paint)
        for side in (1.0, -1.0):
            b.add(beam((x_s, side * 0.6 * w_rear, _top(lay, x_s) - 0.01), (x_s, side * 0.6 * w_rear, z_s),
                       0.012, 0.006), trim)


def _add_bed(b: MeshBuilder, lay: CarLayout) -> None:
    """Open pickup bed: two side walls and a tailgate above the lowered bed floor, and the cab's rear glass."""
    p, d = lay.p, lay.p.dims
    x0, x1 = lay.glass_back, -0.5 + 0.004
    floor, belt = d["belt"] - 0.1, d["belt"]
    t = 0.012
    w_mid = _hw(lay, (x0 + x1) / 2)
    for side in (1.0, -1.0):
        b.add(box((x0 - x1, t, belt - floor + 0.02), ((x0 + x1) / 2, side * (w_mid - t / 2), (belt + floor) / 2 - 0.01)),
              p.paint)
    b.add(box((t, 2 * w_mid, belt - floor + 0.02), (x1 + t / 2, 0.0, (belt + floor) / 2 - 0.01)), p.paint)
    glass = Material("glass", (0.07, 0.09, 0.11), specular=0.9, shininess=90.0, reflect=0.22)
    hw = _hw(lay, x0) * 0.55
    b.add(box((0.004, 2 * hw, 0.45 * (d["roof"] - belt)), (x0 - 0.0015, 0.0, belt + 0.55 * (d["roof"] - belt))),
          glass)
