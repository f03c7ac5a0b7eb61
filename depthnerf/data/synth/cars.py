"""Procedural cars: seven body styles with sampled proportions, wheels, glasshouse, lights and paint.

A car is built at length 1 along +x (front at +x, left at +y, wheels standing on z = 0) and normalised by
:meth:`MeshBuilder.build` to a unit bounding-box diagonal centred at the origin (ShapeNet/SRN normalisation: the
length ends up ~0.85-0.93, the ground below the origin).

Construction: the lower body is a loft of rounded (superelliptic) cross-sections along x whose bottom line rises
over circular wheel arches and whose ends are rounded in plan and profile; the glasshouse is three lofts
(windscreen, roof, rear) of trapezoid sections with rounded roof edges, coloured per face into glass, pillars and
roof; wheels are lathed tyres with disc, dish or spoked rims; lamps, grille, bumpers, mirrors, pickup bed walls
and spoilers are small solids. Styles differ in every proportion (hood, cabin and overhang lengths, heights,
windscreen rake, rear shape), not only in noise.
"""

from __future__ import annotations

import numpy as np

from depthnerf.data.synth.car_layout import CarLayout, CarParams, layout
from depthnerf.data.synth.car_parts import add_details, add_wheels
from depthnerf.data.synth.primitives import Material, MeshBuilder, SynthMesh, loft_indexed

CAR_REVISION = 2
"""Revision of the car grammar; bump whenever the same seed would give a different car (2: mirrors attached)."""
CAR_STYLES = ("sedan", "hatchback", "wagon", "suv", "van", "pickup", "sports")
"""Body styles of the standard family (training and test data), sampled uniformly."""
HELDOUT_CAR_STYLES = ("microcar",)
"""Body styles of the held-out family (``depthnerf synth --family heldout``): never in the standard family. A
microcar is short and tall (height/length ~0.6 against 0.25-0.5), with a stub bonnet and an upright tail."""

PAINTS = (
    ("white", (0.9, 0.9, 0.88)), ("black", (0.06, 0.06, 0.07)), ("silver", (0.68, 0.7, 0.72)),
    ("grey", (0.38, 0.4, 0.42)), ("red", (0.72, 0.08, 0.07)), ("dark red", (0.42, 0.05, 0.07)),
    ("blue", (0.12, 0.26, 0.62)), ("navy", (0.07, 0.1, 0.24)), ("light blue", (0.45, 0.62, 0.78)),
    ("green", (0.12, 0.36, 0.2)), ("yellow", (0.92, 0.76, 0.12)), ("orange", (0.9, 0.42, 0.08)),
    ("beige", (0.78, 0.7, 0.55)), ("brown", (0.34, 0.21, 0.13)),
)
"""Paint colours (name, albedo), jittered per object."""

# (lo, hi) ranges per style, in units of the car length. belt/roof/sill are heights above the ground; hood,
# screen, roof_len and rear_len are x lengths of the bonnet, windscreen, roof and rear window (rear_len 0: upright
# tail), overhangs are bumper-to-axle distances.
_STYLE_RANGES: dict[str, dict[str, tuple[float, float]]] = {
    "sedan": dict(width=(0.38, 0.42), wheel=(0.064, 0.074), sill=(0.045, 0.055), belt=(0.19, 0.215),
                  roof=(0.28, 0.31), hood=(0.28, 0.34), screen=(0.13, 0.17), roof_len=(0.17, 0.23),
                  rear_len=(0.1, 0.14), front_oh=(0.17, 0.21), rear_oh=(0.2, 0.24)),
    "hatchback": dict(width=(0.42, 0.46), wheel=(0.074, 0.084), sill=(0.05, 0.06), belt=(0.22, 0.25),
                      roof=(0.34, 0.37), hood=(0.24, 0.29), screen=(0.14, 0.18), roof_len=(0.24, 0.32),
                      rear_len=(0.05, 0.09), front_oh=(0.14, 0.17), rear_oh=(0.11, 0.14)),
    "wagon": dict(width=(0.37, 0.41), wheel=(0.064, 0.074), sill=(0.045, 0.055), belt=(0.19, 0.215),
                  roof=(0.29, 0.32), hood=(0.27, 0.32), screen=(0.13, 0.16), roof_len=(0.4, 0.46),
                  rear_len=(0.025, 0.05), front_oh=(0.17, 0.2), rear_oh=(0.19, 0.23)),
    "suv": dict(width=(0.4, 0.45), wheel=(0.085, 0.098), sill=(0.07, 0.09), belt=(0.27, 0.31),
                roof=(0.4, 0.45), hood=(0.25, 0.3), screen=(0.12, 0.15), roof_len=(0.36, 0.44),
                rear_len=(0.02, 0.05), front_oh=(0.15, 0.18), rear_oh=(0.15, 0.19)),
    "van": dict(width=(0.37, 0.41), wheel=(0.07, 0.08), sill=(0.055, 0.065), belt=(0.23, 0.27),
                roof=(0.43, 0.5), hood=(0.08, 0.14), screen=(0.1, 0.14), roof_len=(0.6, 0.7),
                rear_len=(0.01, 0.03), front_oh=(0.12, 0.15), rear_oh=(0.13, 0.17)),
    "pickup": dict(width=(0.36, 0.4), wheel=(0.082, 0.094), sill=(0.07, 0.08), belt=(0.27, 0.3),
                   roof=(0.39, 0.43), hood=(0.25, 0.3), screen=(0.11, 0.14), roof_len=(0.12, 0.17),
                   rear_len=(0.0, 0.0), front_oh=(0.15, 0.18), rear_oh=(0.18, 0.23)),
    "microcar": dict(width=(0.52, 0.58), wheel=(0.09, 0.1), sill=(0.06, 0.07), belt=(0.3, 0.34),
                     roof=(0.56, 0.62), hood=(0.1, 0.14), screen=(0.15, 0.19), roof_len=(0.3, 0.38),
                     rear_len=(0.02, 0.04), front_oh=(0.1, 0.12), rear_oh=(0.08, 0.1)),
    "sports": dict(width=(0.44, 0.49), wheel=(0.07, 0.08), sill=(0.032, 0.042), belt=(0.155, 0.175),
                   roof=(0.235, 0.265), hood=(0.33, 0.4), screen=(0.16, 0.2), roof_len=(0.08, 0.13),
                   rear_len=(0.18, 0.26), front_oh=(0.14, 0.17), rear_oh=(0.15, 0.19)),
}


def sample_car(rng: np.random.Generator, style: str | None = None, family: str = "standard") -> CarParams:
    """Draw a car; ``style`` forces a body style (default: uniform over :data:`CAR_STYLES`, or over
    :data:`HELDOUT_CAR_STYLES` for ``family="heldout"``)."""
    style = style or str(rng.choice(CAR_STYLES if family == "standard" else HELDOUT_CAR_STYLES))
    dims = {k: float(rng.uniform(lo, hi)) for k, (lo, hi) in _STYLE_RANGES[style].items()}
    name, base = PAINTS[int(rng.integers(len(PAINTS)))]
    albedo = tuple(float(np.clip(c + rng.uniform(-0.04, 0.04), 0.0, 1.0)) for c in base)
    paint = Material("paint", albedo, specular=0.5, shininess=60.0, reflect=0.06)
    rim_colors = ((0.75, 0.76, 0.78), (0.2, 0.2, 0.22), (0.55, 0.56, 0.58), (0.7, 0.6, 0.35))
    return CarParams(
        style=style, dims=dims, paint=paint, paint_name=name,
        roof=str(rng.choice(["paint", "contrast", "glass"], p=[0.7, 0.2, 0.1])),
        blackout_pillars=bool(rng.random() < 0.4),
        rim=str(rng.choice(["disc", "dish", "spokes"])),
        rim_color=rim_colors[int(rng.integers(len(rim_colors)))],
        cladding=style in ("suv", "pickup") and bool(rng.random() < 0.6),
        spoiler=style == "sports" and bool(rng.random() < 0.5),
        cargo=style == "van" and bool(rng.random() < 0.4),
    )


def _body_stations(lay: CarLayout) -> np.ndarray:
    r, arch = lay.nose_radius, 1.13 * lay.p.dims["wheel"]
    xs = [np.linspace(-0.5, 0.5, 40)]
    ang = np.linspace(0, np.pi / 2, 7)
    xs += [0.5 - r + r * np.sin(ang), -0.5 + r - r * np.sin(ang)]
    for ax in lay.axles:
        xs.append(ax + arch * np.sin(np.linspace(-np.pi / 2, np.pi / 2, 15)))
        xs.append(np.array([ax - arch - 0.004, ax + arch + 0.004]))
    if lay.p.style == "pickup":
        xs.append(np.array([lay.glass_back - 0.002, lay.glass_back + 0.002]))
    x = np.unique(np.round(np.concatenate(xs), 5))
    return x[(x >= -0.5) & (x <= 0.5)]


def _section(half_w: float, z_lo: float, z_hi: float, k: int) -> np.ndarray:
    """Rounded cross-section (superellipse, rounder on top) as ``k x 2`` (y, z), counter-clockwise from +x."""
    t = np.linspace(0, 2 * np.pi, k + 1)[:-1] - np.pi / 2
    c, s = np.cos(t), np.sin(t)
    n = np.where(s > 0, 3.2, 6.0)
    zc, hh = (z_lo + z_hi) / 2, max((z_hi - z_lo) / 2, 1e-4)
    return np.stack([half_w * np.sign(c) * np.abs(c) ** (2 / n), zc + hh * np.sign(s) * np.abs(s) ** (2 / n)], 1)


def _add_body(b: MeshBuilder, lay: CarLayout, trim: Material) -> None:
    x = _body_stations(lay)
    w, lo, hi = lay.half_width(x), lay.bottom(x), lay.top(x)
    k = 28
    rings = np.stack([np.column_stack([np.full(k, xi), _section(wi, li, hi_, k)])
                      for xi, wi, li, hi_ in zip(x, w, lo, hi, strict=True)])
    part, _, ring_idx = loft_indexed(rings)
    if lay.p.cladding:
        z_lo = rings[:, :, 2].min()
        low = np.array([rings[:, j, 2].mean() < z_lo + 0.35 * (lay.p.dims["belt"] - z_lo) for j in range(k)])
        choice = np.where(ring_idx >= 0, low[np.maximum(ring_idx, 0)].astype(int), 0)
        b.add(part, [lay.p.paint, trim], choice)
    else:
        b.add(part, lay.p.paint)


def _cabin_section(half_bot: float, half_top: float, z_lo: float, z_hi: float) -> np.ndarray:
    """Glasshouse cross-section (y, z), counter-clockwise from +x: right side, roof edge, crowned roof, left."""
    e = min(0.22 * half_top, 0.3 * (z_hi - z_lo))
    crown = 0.006
    pts = [(half_bot, z_lo), (half_top, z_hi - e), (half_top - 0.4 * e, z_hi - 0.25 * e),
           (half_top - e, z_hi), (0.45 * half_top, z_hi + 0.7 * crown), (0.0, z_hi + crown),
           (-0.45 * half_top, z_hi + 0.7 * crown), (-(half_top - e), z_hi), (-(half_top - 0.4 * e), z_hi - 0.25 * e),
           (-half_top, z_hi - e), (-half_bot, z_lo)]
    return np.array(pts)


# ring segments of _cabin_section: 0 and 9 sides, 1-2 and 7-8 roof edges, 3-6 roof top, 10 bottom (hidden)
_SIDE, _EDGE, _TOP = (0, 9), (1, 2, 7, 8), (3, 4, 5, 6)


def _add_glasshouse(b: MeshBuilder, lay: CarLayout, glass: Material, pillar: Material, roof: Material) -> None:
    d, p = lay.p.dims, lay.p
    z_roof = d["roof"]
    pw = 0.02  # pillar width
    sink = 0.03

    def ring(x: float, z_top: float) -> np.ndarray:
        w = float(lay.half_width(np.array([x]))[0])
        zb = float(lay.top(np.array([x]))[0]) - sink
        zt = max(z_top, zb + sink + 0.004)
        sec = _cabin_section(0.9 * w, (0.74 if p.style != "van" else 0.8) * w, zb, zt)
        return np.column_stack([np.full(len(sec), x), sec])

    belt_at = lambda x: float(lay.top(np.array([x]))[0])  # noqa: E731
    # windscreen: from the bonnet (height ~ belt) up to the roof
    xs = np.linspace(lay.screen_base, lay.screen_top, 4)[::-1]
    zs = np.linspace(belt_at(lay.screen_base) + 0.004, z_roof, 4)[::-1]
    part, st, rj = loft_indexed(np.stack([ring(x, z) for x, z in zip(xs, zs, strict=True)]))
    is_glass = np.isin(rj, _TOP)
    b.add(part, [pillar, glass], is_glass.astype(int))

    # roof with side windows between pillars
    roof_len = lay.screen_top - lay.roof_back
    n_pillars = {"wagon": 2, "suv": 2, "van": 2, "hatchback": 1, "sedan": 1, "microcar": 1}.get(p.style, 0)
    pillar_x = [lay.screen_top - roof_len * (i + 1) / (n_pillars + 1) for i in range(n_pillars)]
    if p.style == "van":
        pillar_x = [lay.screen_top - 0.14]
    cuts = [lay.screen_top, lay.screen_top - pw]
    for px in pillar_x:
        cuts += [px + pw / 2, px - pw / 2]
    cuts += [lay.roof_back + pw, lay.roof_back]
    xs = np.array(cuts)
    zs = z_roof + 0.004 * np.sin(np.pi * (lay.screen_top - xs) / max(roof_len, 1e-3))
    part, st, rj = loft_indexed(np.stack([ring(x, z) for x, z in zip(xs, zs, strict=True)]))
    n_int = len(xs) - 1
    window = np.zeros(n_int, dtype=bool)
    window[1:n_int - 1:2] = True
    if p.cargo:
        window[2:] = False
    side_glass = np.isin(rj, _SIDE) & window[np.clip(st, 0, n_int - 1)] & (st >= 0)
    top = np.isin(rj, _TOP) & (st >= 0)
    choice = np.where(side_glass, 1, np.where(top, 2, 0))
    b.add(part, [pillar, glass, roof], choice)

    # rear window (or upright tail glass / pickup cab back)
    if lay.roof_back - lay.glass_back > 1e-3:
        xs = np.linspace(lay.roof_back, lay.glass_back, 3)
        zs = np.linspace(z_roof, belt_at(lay.glass_back) + 0.012, 3)
        part, st, rj = loft_indexed(np.stack([ring(x, z) for x, z in zip(xs, zs, strict=True)]))
        b.add(part, [pillar, glass], np.isin(rj, _TOP).astype(int))


def build_car(p: CarParams) -> SynthMesh:
    """Assemble the mesh of one car, normalised to a unit bounding-box diagonal centred at the origin."""
    lay = layout(p)
    b = MeshBuilder()
    trim = Material("plastic", (0.09, 0.09, 0.1), specular=0.15, shininess=20.0)
    glass = Material("glass", (0.07, 0.09, 0.11), specular=0.9, shininess=90.0, reflect=0.22)
    pillar = trim if p.blackout_pillars else p.paint
    roof = {"paint": p.paint, "glass": glass}.get(p.roof)
    if roof is None:
        dark = sum(p.paint.albedo) / 3 > 0.5
        roof = Material("paint", (0.07, 0.07, 0.08) if dark else (0.9, 0.9, 0.88), specular=0.5, shininess=60.0,
                        reflect=0.06)
    _add_body(b, lay, trim)
    _add_glasshouse(b, lay, glass, pillar, roof)
    add_wheels(b, lay)
    add_details(b, lay, trim)
    return b.build(diagonal=1.0)


def car_style_summary(p: CarParams) -> dict[str, str]:
    """What the dataset card records about a car."""
    return {"style": p.style, "paint": p.paint_name, "rim": p.rim, "roof": p.roof}
