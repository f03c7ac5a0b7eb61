"""Vertex colours of an extracted mesh, read from the radiance field (and the photo). Three rules
(:data:`MESH_COLOR_RULES`):

``normal-ray`` (:data:`NORMAL_RAY`, :func:`normal_ray_colors`; what ``photo`` keeps where the photo does not see)
    **the colour the volume renderer gives a short ray that looks at the vertex from outside, along its inward
    normal.** For a vertex ``v`` with unit outward normal ``n`` and a half-width ``h``, the ray starts at ``v + h n``
    and runs along ``d = -n`` to ``v - h n``; its ``S`` samples are ``x_k = v + (h - t_k) n``, ``t_k = 2 h k /
    (S - 1)``, each seen along ``d``. With the renderer's weights ``w_k = alpha_k T_k`` over intervals ``2 h / (S -
    1)`` (:func:`depthnerf.render.volume.render_weights`), the colour is ``c(v) = sum_k w_k c_k / sum_k w_k``: the
    composited colour, normalised by the ray's opacity (no background is mixed in). Where the opacity is below
    :data:`MIN_OPACITY` (no density near the vertex) the colour is the field's colour at ``v`` seen along ``d``.
``point`` (:data:`POINT`, :func:`point_colors`)
    **the field's colour at the vertex itself, seen along the input camera's ray through it.**
``photo`` (:data:`~depthnerf.render.photo_colors.PHOTO`, :func:`~depthnerf.render.photo_colors.photo_blend`; the
    default of reconstruct)
    **the input photo's colour where the input camera sees the vertex or, on a mirror-symmetric object, its mirror
    image; elsewhere the** ``normal-ray`` **colour**, blended over grazing angles, or with a fill the photo's colours
    spread over the surface into it.

Why ``normal-ray``: training fits only the weighted sum of colours along rays, so the colour at one point of a
soft density is barely constrained, and a vertex lies on a density level, often at the surface's fringe. ``point``
therefore gives speckled vertex colours (reds and blues on a green chair), and on the side away from the input
camera it asks for the colour of a surface seen from behind, which no training ray showed. ``normal-ray`` asks what
the renderer shows: the first surface met from outside, seen from outside. Why ``photo``: where the photo sees the
surface its colours are the truth, not the field's blurred and darkened guess. docs/RESULTS.md, "Mesh vertex
colours" measures all three (``scripts/mesh_color_study.py``).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
import trimesh
from jaxtyping import Float
from torch import Tensor

from depthnerf.errors import DepthnerfError
from depthnerf.render.mesh_level import query_chunks
from depthnerf.render.photo_colors import PHOTO, PhotoView, photo_blend
from depthnerf.render.volume import render_weights

NORMAL_RAY = "normal-ray"
"""Colour rule: the volume-rendered colour of a short ray along the inward normal (:func:`normal_ray_colors`)."""
POINT = "point"
"""Colour rule: the field's colour at the vertex, seen along the input camera's ray (:func:`point_colors`)."""
MESH_COLOR_RULES = (NORMAL_RAY, PHOTO, POINT)
"""The vertex colour rules, by name."""
MIN_OPACITY = 1e-3
"""``normal-ray``: below this opacity along the short ray a vertex takes its point colour seen along ``-n``."""

RadianceFn = Callable[[Float[Tensor, "N S 3"], Float[Tensor, "N 3"]],
                      tuple[Float[Tensor, "N S 3"], Float[Tensor, "N S"]]]
"""World points of N rays (S each) and each ray's unit viewing direction -> (RGB in [0, 1], density)."""


def check_color_rule(rule: str) -> None:
    """One line naming ``--mesh-colors`` when ``rule`` is not one of :data:`MESH_COLOR_RULES`."""
    if rule not in MESH_COLOR_RULES:
        raise DepthnerfError(f"--mesh-colors must be one of {', '.join(MESH_COLOR_RULES)}, got {rule!r}")


def normal_ray_colors(radiance_fn: RadianceFn, vertices: Float[Tensor, "N 3"], normals: Float[Tensor, "N 3"],
                      half_width: float, samples: int, chunk: int) -> Float[np.ndarray, "N 3"]:
    """``normal-ray`` colours (module docstring) of ``vertices`` with unit outward ``normals``: ``samples`` samples
    over ``[v + half_width n, v - half_width n]``, ``chunk`` points per field call. Returns float32 ``(N, 3)``."""
    if not half_width > 0 or samples < 2:
        raise DepthnerfError(f"mesh colours: the normal ray needs a half-width > 0 and >= 2 samples, got "
                             f"{half_width} and {samples}")
    t = torch.linspace(0.0, 2.0 * half_width, samples, device=vertices.device, dtype=vertices.dtype)
    interval = torch.full((samples,), 2.0 * half_width / (samples - 1), device=vertices.device,
                          dtype=vertices.dtype)

    def colors(rows: Tensor) -> Tensor:
        v, n = vertices[rows], normals[rows]
        points = (v + half_width * n)[:, None, :] - n[:, None, :] * t[None, :, None]
        rgb, sigma = radiance_fn(points, -n)
        weights, _ = render_weights(sigma, interval.expand_as(sigma))
        opacity = weights.sum(-1)
        color = (weights[..., None] * rgb).sum(-2) / opacity.clamp_min(MIN_OPACITY)[:, None]
        faint = opacity < MIN_OPACITY
        if faint.any():  # no density near the vertex: its own colour, seen along -n
            color[faint] = radiance_fn(v[faint, None, :], -n[faint])[0][:, 0]
        return color

    rows = torch.arange(len(vertices), device=vertices.device)
    return query_chunks(colors, lambda a, b: rows[a:b], len(vertices), max(1, chunk // samples), 3,
                        "the field's colour")


def seen_from(radiance_fn: RadianceFn, points: Float[Tensor, "N 3"], eye: Float[Tensor, " 3"]
              ) -> tuple[Float[Tensor, "N 3"], Float[Tensor, " N"]]:
    """``(rgb, density)`` of the field at each point, seen along the ray from ``eye`` through it."""
    dirs = torch.nn.functional.normalize(points - eye.to(points), dim=-1)
    rgb, sigma = radiance_fn(points[:, None, :], dirs)
    return rgb[:, 0], sigma[:, 0]


def point_colors(radiance_fn: RadianceFn, vertices: Float[Tensor, "N 3"], eye: Float[Tensor, " 3"], chunk: int
                 ) -> Float[np.ndarray, "N 3"]:
    """``point`` colours (module docstring): the field at each vertex seen along the ray from ``eye`` (the input
    camera centre) through it (:func:`seen_from`). Returns float32 ``(N, 3)``."""
    return query_chunks(lambda points: seen_from(radiance_fn, points, eye)[0], lambda a, b: vertices[a:b],
                        len(vertices), chunk, 3, "the field's colour")


def vertex_colors(rule: str, radiance_fn: RadianceFn, mesh: trimesh.Trimesh, eye: Float[Tensor, " 3"],
                  half_width: float, samples: int, chunk: int, device: torch.device | str = "cpu",
                  photo: PhotoView | None = None, fill: float = 0.0) -> Float[np.ndarray, "N 4"]:
    """RGBA uint8 colours of ``mesh``'s vertices by ``rule`` (:data:`MESH_COLOR_RULES`), alpha 255; ``photo``: the
    input photo (the ``photo`` rule needs it), ``fill``: its fill
    (:func:`~depthnerf.render.photo_colors.photo_blend`)."""
    check_color_rule(rule)
    if rule == PHOTO and photo is None:
        raise DepthnerfError("mesh colours: the photo rule needs the input photo")
    v = torch.as_tensor(np.array(mesh.vertices), dtype=torch.float32, device=device)
    if rule == POINT:
        rgb = point_colors(radiance_fn, v, eye.to(device), chunk)
    else:
        n = torch.as_tensor(np.array(mesh.vertex_normals), dtype=torch.float32, device=device)
        rgb = normal_ray_colors(radiance_fn, v, n, half_width, samples, chunk)
        if rule == PHOTO:
            rgb = photo_blend(mesh, rgb, photo, fill)
    return np.concatenate([np.round(np.clip(rgb, 0, 1) * 255), np.full((len(rgb), 1), 255)], axis=1).astype(np.uint8)


def describe_colors(rule: str, half_width: float, fill: float = 0.0) -> str:
    """One line for records (the reconstruction manifest)."""
    if rule == NORMAL_RAY:
        return (f"fine-network rgb volume-rendered along each vertex's inward normal, from {half_width:g} outside "
                f"the surface to {half_width:g} inside")
    if rule == PHOTO:
        spread = (f"its colours spread over the surface for {fill:g} x their RMS distance to the field's (world "
                  "units), into ") if fill > 0 else ""
        return "the input photo's rgb where it sees the vertex or its mirror image; elsewhere " + spread + \
            describe_colors(NORMAL_RAY, half_width)
    return "fine-network rgb at each vertex seen along the input camera's ray"
