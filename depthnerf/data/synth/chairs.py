"""Procedural chairs: six archetypes combining leg, seat, back and arm types with varied materials.

A chair is built with the floor at z = 0, the seat centred over the origin, its front towards +x and its left
towards +y, then normalised by :meth:`MeshBuilder.build` to a bounding-box diagonal centred at the origin: 1.0 as
ShapeNet normalises its objects (the SRN framing), or :data:`CHAIR_DIAGONAL` = 1.35 in the legacy framing, which
made chairs fill ~50-70% of the frame height at SRN's chair camera radius of 2.0. Both stay inside pixelNeRF's
chair z-range 1.25-2.75.

Archetypes pick compatible parts (a swivel base gets an office back, a lounge chair solid side panels...):

=========== ========================= ============================================ ======================
archetype   legs                      back                                         arms
=========== ========================= ============================================ ======================
dining      four (square/round,       solid, curved, vertical slats, ladder,       none or posts
            tapered, splayed;         spindles, splat
            stretchers)
office      swivel (5-star, casters)  office (padded, on a stem)                   none or office
sled        sled / cantilever tubes   curved shell, solid, ladder                  none or tube
armchair    panel or short four       cushioned solid                              panel (solid sides)
bar         tall four + foot ring     low ladder, solid or splat                   none
pedestal    pedestal (tulip) base     curved shell                                 none or shell
hybrid      swivel, pedestal or sled  slats, spindles, splat or ladder             none
=========== ========================= ============================================ ======================

``hybrid`` is the held-out family (``depthnerf synth --family heldout``), never drawn in the standard family.
"""

from __future__ import annotations

import numpy as np

from depthnerf.data.synth.chair_params import ChairParams
from depthnerf.data.synth.chair_parts import add_arms, add_back, add_legs, add_seat
from depthnerf.data.synth.primitives import Material, MeshBuilder, SynthMesh

CHAIR_REVISION = 2
"""Revision of the chair grammar; bump whenever the same seed would give a different chair (2: weighted
archetypes)."""
CHAIR_ARCHETYPES = ("dining", "office", "sled", "armchair", "bar", "pedestal")
"""Chair archetypes."""
ARCHETYPE_WEIGHTS = (0.3, 0.18, 0.12, 0.15, 0.1, 0.15)
"""Sampling probabilities of :data:`CHAIR_ARCHETYPES` (four-legged chairs dominate ShapeNet chairs)."""
HELDOUT_ARCHETYPES = ("hybrid",)
"""Archetypes of the held-out family (``depthnerf synth --family heldout``): a swivel, pedestal or sled base
under a post-and-rail back (slats, spindles, splat or ladder): a leg/back mix the standard family never builds
(there, post-and-rail backs stand on four legs; swivel bases carry office backs, pedestals shells)."""

CHAIR_DIAGONAL = 1.35
"""Bounding-box diagonal of a normalised chair in the legacy framing (world units); the SRN framing uses 1.0."""

WOODS = (("oak", (0.72, 0.55, 0.35)), ("walnut", (0.36, 0.23, 0.14)), ("cherry", (0.55, 0.29, 0.17)),
         ("beech", (0.82, 0.68, 0.5)), ("white lacquer", (0.88, 0.87, 0.84)), ("black lacquer", (0.1, 0.1, 0.1)))
"""Wood finishes (name, albedo)."""
METALS = (("chrome", (0.74, 0.75, 0.77), 0.5), ("black metal", (0.12, 0.12, 0.13), 0.1),
          ("aluminium", (0.6, 0.61, 0.63), 0.25))
"""Metal finishes (name, albedo, reflectance)."""
PLASTICS = (("white", (0.9, 0.9, 0.88)), ("black", (0.08, 0.08, 0.09)), ("red", (0.75, 0.12, 0.1)),
            ("yellow", (0.92, 0.75, 0.2)), ("blue", (0.15, 0.3, 0.65)), ("green", (0.3, 0.55, 0.3)),
            ("grey", (0.55, 0.56, 0.57)), ("orange", (0.92, 0.45, 0.12)))
"""Plastic colours."""
FABRICS = (("grey", (0.5, 0.5, 0.52)), ("charcoal", (0.2, 0.2, 0.22)), ("beige", (0.76, 0.68, 0.55)),
           ("navy", (0.12, 0.16, 0.32)), ("burgundy", (0.45, 0.1, 0.14)), ("teal", (0.12, 0.45, 0.45)),
           ("mustard", (0.78, 0.6, 0.15)), ("olive", (0.4, 0.42, 0.2)), ("cream", (0.9, 0.86, 0.76)),
           ("tan leather", (0.6, 0.38, 0.2)), ("black leather", (0.07, 0.07, 0.08)))
"""Upholstery colours."""


def _pick(rng: np.random.Generator, table: tuple) -> tuple:
    return table[int(rng.integers(len(table)))]


def _jitter(rng: np.random.Generator, rgb: tuple[float, float, float], amount: float = 0.03) -> tuple:
    return tuple(float(np.clip(c + rng.uniform(-amount, amount), 0, 1)) for c in rgb)


def _materials(rng: np.random.Generator, archetype: str) -> tuple[Material, Material, Material, str]:
    wood_name, wood = _pick(rng, WOODS)
    metal_name, metal_rgb, metal_refl = _pick(rng, METALS)
    plastic_name, plastic = _pick(rng, PLASTICS)
    fabric_name, fabric_rgb = _pick(rng, FABRICS)
    wood_m = Material("wood", _jitter(rng, wood), specular=0.15, shininess=20.0)
    metal_m = Material("metal", _jitter(rng, metal_rgb, 0.02), specular=0.8, shininess=70.0, reflect=metal_refl)
    plastic_m = Material("plastic", _jitter(rng, plastic), specular=0.35, shininess=40.0, reflect=0.03)
    leather = "leather" in fabric_name
    fabric_m = Material("leather" if leather else "fabric", _jitter(rng, fabric_rgb),
                        specular=0.25 if leather else 0.04, shininess=25.0 if leather else 8.0)
    if archetype in ("dining", "bar"):
        frame, fname = (wood_m, wood_name) if rng.random() < 0.7 else (metal_m, metal_name)
        seat, sname = (frame, fname) if rng.random() < 0.6 else (plastic_m, plastic_name)
        if frame.name == "wood" and rng.random() < 0.5:
            seat, sname = frame, fname
    elif archetype == "office":
        black = Material("plastic", (0.08, 0.08, 0.09), specular=0.35, shininess=40.0)
        frame, fname = (black, "black plastic") if rng.random() < 0.6 else (metal_m, metal_name)
        seat, sname = fabric_m, fabric_name
    elif archetype == "sled":
        frame, fname = metal_m, metal_name
        seat, sname = (plastic_m, plastic_name) if rng.random() < 0.6 else (wood_m, wood_name)
    elif archetype == "armchair":
        frame, fname = (wood_m, wood_name) if rng.random() < 0.5 else (fabric_m, fabric_name)
        seat, sname = fabric_m, fabric_name
    else:  # pedestal
        frame, fname = (metal_m, metal_name) if rng.random() < 0.5 else (plastic_m, plastic_name)
        seat, sname = plastic_m, plastic_name
    return frame, seat, fabric_m, f"{fname}/{sname}/{fabric_name}"


def sample_chair(rng: np.random.Generator, archetype: str | None = None, family: str = "standard") -> ChairParams:
    """Draw a chair; ``archetype`` forces one (default: drawn with :data:`ARCHETYPE_WEIGHTS`, or uniformly from
    :data:`HELDOUT_ARCHETYPES` for ``family="heldout"``)."""
    if family == "standard":
        a = archetype or str(rng.choice(CHAIR_ARCHETYPES, p=ARCHETYPE_WEIGHTS))
    else:
        a = archetype or str(rng.choice(HELDOUT_ARCHETYPES))
    u = rng.uniform
    choice = lambda options, p=None: str(rng.choice(options, p=p))  # noqa: E731
    dims = dict(seat_h=u(0.43, 0.5), seat_w=u(0.42, 0.54), seat_d=u(0.4, 0.5), seat_t=u(0.025, 0.05),
                back_h=u(0.38, 0.58), back_tilt=np.radians(u(3, 14)), leg_t=u(0.026, 0.042), splay=u(0.0, 0.04),
                back_curve=u(0.0, 0.5), arm_h=u(0.19, 0.26), cushion_t=u(0.04, 0.08), panel_t=u(0.07, 0.14))
    opts = dict(n_slats=int(rng.integers(3, 8)), round_legs=int(rng.random() < 0.4), tapered=int(rng.random() < 0.5),
                stretchers=int(rng.choice([0, 1, 2], p=[0.45, 0.3, 0.25])), seat_cushion=int(rng.random() < 0.35),
                back_cushion=0, cantilever=int(rng.random() < 0.4), headrest=int(rng.random() < 0.3),
                star_phase=int(rng.integers(72)))
    seat_shape = choice(["rect", "rounded", "trapezoid"], [0.45, 0.3, 0.25])
    if a == "dining":
        legs, back = "four", choice(["solid", "curved", "slats", "ladder", "spindles", "splat"])
        arms = choice(["none", "posts"], [0.7, 0.3])
    elif a == "office":
        legs, back, arms = "swivel", "office", choice(["none", "office"], [0.35, 0.65])
        dims.update(seat_h=u(0.46, 0.53), seat_w=u(0.46, 0.54), back_h=u(0.45, 0.65), seat_t=u(0.05, 0.08))
        seat_shape = "rounded"
    elif a == "sled":
        legs, back = "sled", choice(["curved", "solid", "ladder"], [0.5, 0.3, 0.2])
        arms = choice(["none", "tube"], [0.6, 0.4])
        opts["round_legs"] = 1
        opts["seat_cushion"] = int(rng.random() < 0.25)
    elif a == "armchair":
        legs, back, arms = choice(["panel", "four"], [0.55, 0.45]), "solid", "panel"
        dims.update(seat_h=u(0.38, 0.45), seat_w=u(0.5, 0.62), seat_d=u(0.5, 0.6), back_h=u(0.35, 0.5),
                    back_tilt=np.radians(u(8, 18)), cushion_t=u(0.08, 0.13), splay=0.0)
        opts.update(seat_cushion=1, back_cushion=int(rng.random() < 0.7), stretchers=0)
        seat_shape = "rect"
    elif a == "bar":
        legs, back, arms = "four", choice(["ladder", "solid", "splat", "none"], [0.35, 0.25, 0.2, 0.2]), "none"
        dims.update(seat_h=u(0.66, 0.8), seat_w=u(0.38, 0.46), seat_d=u(0.36, 0.44), back_h=u(0.2, 0.34),
                    splay=u(0.02, 0.06))
        opts["stretchers"] = 3
        seat_shape = choice(["rect", "round"])
    elif a == "hybrid":  # held-out family
        legs = choice(["swivel", "pedestal", "sled"])
        back = choice(["slats", "spindles", "splat"] + (["ladder"] if legs != "sled" else []))
        arms = "none"
        opts["round_legs"] = 1
        seat_shape = choice(["rounded", "round"])
    else:  # pedestal
        legs, back, arms = "pedestal", "shell", choice(["none", "shell"], [0.6, 0.4])
        dims.update(back_curve=u(0.5, 0.9), seat_w=u(0.44, 0.52))
        seat_shape = "round"
    frame, seat, cushion, finish = _materials(rng, a)
    return ChairParams(a, legs, back, arms, seat_shape, {k: float(v) for k, v in dims.items()}, opts, frame, seat,
                       cushion, finish)


def build_chair(p: ChairParams, diagonal: float = CHAIR_DIAGONAL) -> SynthMesh:
    """Assemble the mesh of one chair, normalised to a bounding-box ``diagonal`` (default: the legacy framing's
    :data:`CHAIR_DIAGONAL`; the SRN framing's is 1.0) centred at the origin."""
    b = MeshBuilder()
    add_seat(b, p)
    add_legs(b, p)
    add_back(b, p)
    add_arms(b, p)
    return b.build(diagonal=diagonal)


def chair_style_summary(p: ChairParams) -> dict[str, str]:
    """What the dataset card records about a chair."""
    return {"style": p.archetype, "legs": p.legs, "back": p.back, "arms": p.arms, "seat": p.seat_shape,
            "finish": p.finish}
