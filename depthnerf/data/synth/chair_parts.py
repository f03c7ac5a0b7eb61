"""Seats, legs, backs and arms of the procedural chairs (frame and units of :mod:`depthnerf.data.synth.chairs`).

Backs are built in a *back frame*: origin at the rear edge of the seating surface, local +x forward, +y left,
local +z up the back, then tilted backwards by ``back_tilt`` about the y axis.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from depthnerf.data.synth.chair_params import ChairParams
from depthnerf.data.synth.primitives import (
    Material,
    MeshBuilder,
    Part,
    beam,
    box,
    cylinder,
    lathe,
    loft,
    merge,
    prism,
    superellipse_outline,
    superellipsoid,
)


@dataclass
class SeatGeom:
    """Where the seat is (nominal units)."""

    z_top: float
    """Height of the seating surface (top of the cushion if any)."""
    z_slab_top: float
    """Top of the seat slab."""
    z_bottom: float
    """Bottom of the seat slab."""
    half_w: float
    """Half width (y)."""
    half_d: float
    """Half depth (x)."""
    inset: float
    """Inset of leg and post centres from the seat edge."""


def seat_geom(p: ChairParams) -> SeatGeom:
    d = p.dims
    cushion = d["cushion_t"] if p.options["seat_cushion"] else 0.0
    slab_top = d["seat_h"] - cushion
    half_w, half_d = d["seat_w"] / 2, d["seat_d"] / 2
    if p.seat_shape == "round":
        half_w = half_d = max(half_w, half_d) * 0.95
    return SeatGeom(d["seat_h"], slab_top, slab_top - d["seat_t"], half_w, half_d, inset=0.9 * d["leg_t"])


def _tilt(p: ChairParams) -> np.ndarray:
    a = p.dims["back_tilt"]
    return np.array([[np.cos(a), 0, -np.sin(a)], [0, 1, 0], [np.sin(a), 0, np.cos(a)]])


def _to_back(p: ChairParams, g: SeatGeom, part: Part) -> Part:
    """Place a part built in the back frame."""
    return part.transformed(_tilt(p), np.array([-g.half_d, 0.0, g.z_top]))


def _stick(p: ChairParams, a: np.ndarray, b: np.ndarray, t: float) -> Part:
    """A leg/post/rail: round (cylinder) or square (beam) depending on the chair."""
    if p.options["round_legs"]:
        return cylinder(a, b, t / 2, 12)
    return beam(a, b, t, t)


def add_seat(b: MeshBuilder, p: ChairParams) -> None:
    """Seat slab (shaped prism or upholstered block) and the optional seat cushion."""
    g = seat_geom(p)
    upholstered = p.archetype in ("office", "armchair")
    if upholstered:
        b.add(superellipsoid((g.half_d, g.half_w, (g.z_slab_top - g.z_bottom) / 2),
                             (0, 0, (g.z_slab_top + g.z_bottom) / 2), 0.3, 0.25, 10, 28),
              p.cushion if p.archetype == "office" else p.frame)
    else:
        shape = {"rect": (8.0, 1.0), "rounded": (3.5, 1.0), "trapezoid": (6.0, 1.15), "round": (2.0, 1.0)}
        n, front = shape[p.seat_shape]
        outline = superellipse_outline(g.half_d, g.half_w / (1 + (front - 1) / 2), n, 48, front)
        b.add(prism(outline, g.z_bottom, g.z_slab_top), p.seat)
    if p.options["seat_cushion"]:
        c = p.dims["cushion_t"]
        b.add(superellipsoid((0.97 * g.half_d, 0.95 * g.half_w, c / 2 + 0.004), (0.01, 0, g.z_slab_top + c / 2 - 0.004),
                             0.3, 0.25, 10, 28), p.cushion)


def add_legs(b: MeshBuilder, p: ChairParams) -> None:
    """The base: four legs (+ stretchers), swivel star, sled runners, pedestal, or a solid plinth."""
    g, d = seat_geom(p), p.dims
    t = d["leg_t"]
    if p.legs == "four":
        feet, tops = [], []
        for sx in (1.0, -1.0):
            for sy in (1.0, -1.0):
                top = np.array([sx * (g.half_d - g.inset), sy * (g.half_w - g.inset), g.z_bottom + 0.005])
                foot = top * [1, 1, 0] + np.array([sx * d["splay"], sy * d["splay"], 0.0])
                feet.append(foot)
                tops.append(top)
                if p.options["round_legs"] and p.options["tapered"]:
                    b.add(cylinder(foot, top, 0.32 * t, 12, radius1=0.55 * t), p.frame)
                else:
                    b.add(_stick(p, foot, top, t), p.frame)
        _add_stretchers(b, p, feet, tops)
    elif p.legs == "swivel":
        metal = p.frame
        b.add(cylinder((0, 0, 0.09), (0, 0, g.z_bottom - 0.03), 0.024, 16), metal)
        b.add(box((0.2, 0.16, 0.035), (0, 0, g.z_bottom - 0.015)), metal)
        b.add(cylinder((0, 0, 0.055), (0, 0, 0.11), 0.045, 16), metal)
        radius = 0.3
        for k in range(5):
            phi = np.radians(p.options["star_phase"]) + 2 * np.pi * k / 5
            tip = np.array([radius * np.cos(phi), radius * np.sin(phi), 0.06])
            b.add(beam((0, 0, 0.085), tip, 0.04, 0.03), metal)
            b.add(superellipsoid((0.026, 0.014, 0.026), tip * [1, 1, 0] + [0, 0, 0.027], 1.0, 1.0, 8, 12,
                                 rotation=_rot_z(phi + np.pi / 2)), _dark(p))
    elif p.legs == "sled":
        _add_sled(b, p, g)
    elif p.legs == "pedestal":
        rb, rc = 0.27, 0.03
        prof = [(0, 0), (rb, 0), (rb, 0.012), (0.6 * rb, 0.028), (0.3 * rb, 0.07), (rc, 0.16), (rc, g.z_bottom + 0.01),
                (0, g.z_bottom + 0.01)]
        b.add(lathe(prof, 32), p.frame)
    elif p.legs == "panel":  # upholstered plinth between the side panels
        b.add(box((2 * g.half_d, 2 * g.half_w, g.z_bottom - 0.03), (0, 0, (g.z_bottom + 0.03) / 2 + 0.004)), p.frame)


def _rot_z(a: float) -> np.ndarray:
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])


def _dark(p: ChairParams) -> Material:
    return Material("plastic", (0.06, 0.06, 0.07), specular=0.3, shininess=30.0)


def _add_stretchers(b: MeshBuilder, p: ChairParams, feet: list, tops: list) -> None:
    kind = p.options["stretchers"]
    if kind == 0:
        return
    t = 0.6 * p.dims["leg_t"]
    frac = 0.38 if kind == 3 else 0.3  # height along the leg
    pts = [f + (tp - f) * frac for f, tp in zip(feet, tops, strict=True)]  # order: (+,+) (+,-) (-,+) (-,-)
    fl, fr, rl, rr = pts
    if kind == 1:  # H: two side rails and a cross rail
        b.add(_stick(p, fl, rl, t), p.frame)
        b.add(_stick(p, fr, rr, t), p.frame)
        b.add(_stick(p, (fl + rl) / 2, (fr + rr) / 2, t), p.frame)
    else:  # box (and the bar-stool foot ring)
        for a, c in ((fl, fr), (fr, rr), (rr, rl), (rl, fl)):
            b.add(_stick(p, a, c, t), p.frame)


def _tube_path(points: list[np.ndarray], r: float) -> Part:
    """Round tube through points with ball joints at the bends."""
    parts = [cylinder(a, c, r, 12) for a, c in zip(points[:-1], points[1:], strict=True)]
    parts += [superellipsoid((r, r, r), q, 1.0, 1.0, 6, 12) for q in points[1:-1]]
    return merge(parts)


def _add_sled(b: MeshBuilder, p: ChairParams, g: SeatGeom) -> None:
    r = 0.013
    for sy in (1.0, -1.0):
        y = sy * (g.half_w - 0.015)
        seat_front = np.array([g.half_d - 0.03, y, g.z_bottom - r])
        seat_rear = np.array([-g.half_d + 0.03, y, g.z_bottom - r])
        if p.options["cantilever"]:
            path = [seat_rear, seat_front, np.array([g.half_d + 0.02, y, r]), np.array([-0.55 * g.half_d, y, r])]
        else:
            path = [seat_rear, seat_front, np.array([g.half_d + 0.01, y, r]), np.array([-g.half_d - 0.02, y, r]),
                    seat_rear]
        b.add(_tube_path(path, r), p.frame)


def _curved_panel(width: float, height: float, thick: float, curve: float, z0: float, wings: float = 0.0,
                  stations: int = 17) -> Part:
    """A back panel bent on a circular arc in plan (sides forward); ``wings`` lowers the sides (tub shell)."""
    phi_max = max(curve, 1e-3)
    radius = (width / 2) / np.sin(min(phi_max, 1.4))
    theta = np.linspace(0, 2 * np.pi, 17)[:-1]
    rings = []
    for phi in np.linspace(-phi_max, phi_max, stations):
        pos = np.array([radius * (1 - np.cos(phi)), radius * np.sin(phi), 0.0])
        nrm = np.array([np.cos(phi), -np.sin(phi), 0.0])
        h = height * (1 - wings * (phi / phi_max) ** 2)
        c, s = np.cos(theta), np.sin(theta)
        a = -(thick / 2) * np.sign(c) * np.abs(c) ** 0.5
        zz = z0 + h / 2 + (h / 2) * np.sign(s) * np.abs(s) ** 0.25
        rings.append(pos[None] + a[:, None] * nrm[None] + zz[:, None] * np.array([0, 0, 1.0])[None])
    return loft(np.stack(rings))


def add_back(b: MeshBuilder, p: ChairParams) -> None:
    """The backrest, in one of the back types (see :class:`~depthnerf.data.synth.chair_params.ChairParams`)."""
    g, d = seat_geom(p), p.dims
    h, t = d["back_h"], d["leg_t"]
    wb = 2 * g.half_w
    if p.back == "none":
        return
    if p.back in ("solid", "curved", "shell"):
        if p.archetype == "armchair":
            thick = 0.1
            width = wb + 2 * d["panel_t"]
            part = superellipsoid((thick / 2, width / 2, (h + g.z_top - g.z_bottom) / 2),
                                  (-thick / 2, 0, (h - (g.z_top - g.z_bottom)) / 2), 0.25, 0.2, 10, 24)
            b.add(_to_back(p, g, part), p.frame)
            if p.options["back_cushion"]:
                cush = superellipsoid((0.05, 0.95 * g.half_w, 0.42 * h), (0.04, 0, 0.48 * h), 0.35, 0.3, 10, 24)
                b.add(_to_back(p, g, cush), p.cushion)
            return
        thick = 0.022 if p.back != "solid" else 0.035
        curve = 0.0 if p.back == "solid" else d["back_curve"]
        wings = 0.45 if (p.back == "shell" and p.arms == "shell") else 0.0
        if wings:
            curve = 1.25
        z0 = -0.01 if p.back == "shell" else 0.06
        part = _curved_panel(wb * (0.95 if p.back != "shell" else 1.0), h - z0, thick, curve, z0, wings)
        b.add(_to_back(p, g, part.transformed(translation=(thick / 2 + 0.005, 0, 0))), p.seat)
        if p.back != "shell":
            _add_posts(b, p, g, h * 0.5)
        return
    if p.back == "office":
        _add_office_back(b, p, g)
        return
    # post-and-rail backs: posts continue the rear legs
    top_rail = 0.05 + 0.03 * (p.back == "splat")
    _add_posts(b, p, g, h)
    y_in = g.half_w - g.inset
    rail_t = 0.6 * t
    b.add(_to_back(p, g, box((rail_t, 2 * y_in, top_rail), (0, 0, h - top_rail / 2))), p.frame)
    n = p.options["n_slats"]
    if p.back == "slats":
        b.add(_to_back(p, g, box((rail_t, 2 * y_in, 0.03), (0, 0, 0.08))), p.frame)
        for y in np.linspace(-y_in, y_in, n + 2)[1:-1]:
            b.add(_to_back(p, g, box((0.5 * rail_t, min(0.045, 1.4 * y_in / n), h - top_rail - 0.08),
                                     (0, y, (h - top_rail + 0.08) / 2))), p.frame)
    elif p.back == "ladder":
        for z in np.linspace(0.3 * h, h - top_rail, max(2, n // 2) + 1)[:-1]:
            b.add(_to_back(p, g, box((rail_t, 2 * y_in, 0.035), (0, 0, z))), p.frame)
    elif p.back == "spindles":
        for y in np.linspace(-y_in, y_in, n + 3)[1:-1]:
            b.add(_to_back(p, g, cylinder((0, y, -0.005), (0, y, h - top_rail / 2), 0.008, 8)), p.frame)
    elif p.back == "splat":
        splat = superellipsoid((0.008, 0.2 * g.half_w + 0.03, (h - top_rail) / 2), (0, 0, (h - top_rail) / 2),
                               0.2, 0.6, 8, 16)
        b.add(_to_back(p, g, splat), p.seat)


def _add_posts(b: MeshBuilder, p: ChairParams, g: SeatGeom, height: float) -> None:
    """Two back posts in the back frame, from the seat bottom (continuing the rear legs) to ``height``."""
    t = p.dims["leg_t"]
    for sy in (1.0, -1.0):
        y = sy * (g.half_w - g.inset)
        x = g.inset
        bottom = -(g.z_top - g.z_bottom) - 0.005
        b.add(_to_back(p, g, _stick(p, np.array([x, y, bottom]), np.array([x, y, height]), t)), p.frame)


def _add_office_back(b: MeshBuilder, p: ChairParams, g: SeatGeom) -> None:
    h = p.dims["back_h"]
    stem_t = 0.05
    b.add(beam((-g.half_d + 0.08, 0, g.z_bottom - 0.02), (-g.half_d - 0.05, 0, g.z_bottom - 0.02), stem_t, 0.02),
          p.frame)
    stem = beam((-0.05, 0, -(g.z_top - g.z_bottom) - 0.02), (-0.05, 0, 0.25 * h), stem_t, 0.02)
    b.add(_to_back(p, g, stem), p.frame)
    pad = superellipsoid((0.04, 0.93 * g.half_w, 0.43 * h), (0.0, 0, 0.1 + 0.43 * h), 0.4, 0.35, 10, 24)
    b.add(_to_back(p, g, pad), p.cushion)
    if p.options["headrest"] and h > 0.52:
        head = superellipsoid((0.035, 0.45 * g.half_w, 0.06), (0.01, 0, 0.1 + 0.86 * h + 0.1), 0.4, 0.4, 8, 20)
        b.add(_to_back(p, g, head), p.cushion)
        b.add(_to_back(p, g, beam((-0.03, 0, 0.1 + 0.8 * h), (-0.02, 0, 0.1 + 0.86 * h + 0.06), 0.04, 0.015)),
              p.frame)


def add_arms(b: MeshBuilder, p: ChairParams) -> None:
    """Armrests: on posts, office T-arms, tube arms, or solid side panels."""
    g, d = seat_geom(p), p.dims
    za = g.z_top + d["arm_h"]
    t = d["leg_t"]
    for sy in (1.0, -1.0):
        if p.arms == "posts":
            y = sy * (g.half_w - 0.3 * g.inset)
            rest = beam((-g.half_d + 0.01, y, za), (g.half_d + 0.02, y, za), 0.05, 0.022)
            b.add(rest, p.frame)
            b.add(_stick(p, np.array([g.half_d - g.inset, y, g.z_slab_top - 0.01]),
                         np.array([g.half_d - g.inset, y, za]), 0.8 * t), p.frame)
        elif p.arms == "office":
            y = sy * (g.half_w + 0.03)
            b.add(beam((0.0, sy * (g.half_w - 0.12), g.z_bottom - 0.012), (0.0, y, g.z_bottom - 0.012), 0.04, 0.02),
                  p.frame)
            b.add(beam((0.0, y, g.z_bottom - 0.02), (0.03, y, za - 0.01), 0.04, 0.02), p.frame)
            b.add(superellipsoid((0.13, 0.035, 0.018), (0.03, y, za), 0.4, 0.4, 8, 16), _pad(p))
        elif p.arms == "tube":
            y = sy * (g.half_w + 0.012)
            path = [np.array([-g.half_d + 0.02, y, za]), np.array([g.half_d - 0.04, y, za]),
                    np.array([g.half_d - 0.04, y, g.z_bottom - 0.013])]
            b.add(_tube_path(path, 0.012), p.frame)
        elif p.arms == "panel":
            pt = d["panel_t"]
            z0 = 0.0 if p.legs == "panel" else g.z_bottom - 0.08
            b.add(superellipsoid((g.half_d + 0.03, pt / 2, (za - z0) / 2), (0.0, sy * (g.half_w + pt / 2 - 0.005),
                                 (za + z0) / 2 + 0.004), 0.2, 0.25, 10, 24), p.frame)


def _pad(p: ChairParams) -> Material:
    return p.cushion if p.frame.name == "plastic" else _dark(p)
