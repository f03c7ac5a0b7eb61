"""The density level of an extracted mesh surface: a fixed number, or a rule resolved per object from the densities
along the input camera's rays.

Every rule reads the same samples: :data:`AUTO_SAMPLES` uniform samples per input ray (every ``ray_stride``-th
pixel row and column) between the run's z-near and z-far, from the density function the mesh samples. Per ray:
the **peak** density, and the **opacity** ``1 - exp(-sum(sigma) * delta)``, what the volume renderer's quadrature
gives for those samples. A ray is **opaque** when its opacity exceeds :data:`OPAQUE` (0.5): the rendered
silhouette of the object seen from the input camera.

``auto`` (:data:`AUTO_LEVEL`, :func:`auto_level`)
    **level = 0.5 x the median, over the opaque rays, of the peak density along the ray.** A ray that renders
    opaque crosses the object, so its peak density is the object's interior density there, and the median over
    those rays is the typical interior density; half of it is the half-maximum level, the classic edge definition
    (it puts the surface of a blurred step at the step). Scale-free: sharp paper-scale models (interior densities in
    the hundreds) get a high level, soft CPU-preset models (peaks ~5) a low one, where a fixed level gives empty
    meshes. The median ignores a few outlier rays. Its weakness: a part thinner or fainter than the typical one (a
    chair's legs, seen beside its seat) peaks below half the median and is dropped, although it renders opaque.

``silhouette`` (:data:`SILHOUETTE_LEVEL`, :func:`silhouette_level`)
    **the level whose surface, seen from the input camera, best matches the object's silhouette there**: the
    input's own object mask when the caller has one (reconstruct and eval do: the photo's mask, the input view's
    mask), else the field's rendered silhouette (the opaque rays). A ray meets the level-``L`` surface exactly when
    its peak density exceeds ``L``, so the mesh's silhouette in the input view is ``S(L) = {rays: peak > L}``; the
    rule picks the ``L`` maximising the intersection over union with the target rays ``M``:
    ``IoU(L) = |S(L) & M| / |S(L) | M|``. It reads every pixel's ray (``ray_stride`` 1): a chair leg is a pixel
    wide at 64 px. Over the rays sorted by peak
    (descending), keeping the first ``k`` gives ``IoU_k = TP_k / (|M| + k - TP_k)`` with ``TP_k`` the opaque rays
    among them, so the search is one sort and one cumulative sum (over the ``k`` that end a run of equal peaks: a
    level keeps all of a tie or none of it; and only ``k`` whose ``k``-th peak is positive, as no positive level
    keeps a ray of peak 0). The level is the midpoint between the ``k*``-th and the next peak (half the ``k*``-th
    when every ray is kept or the next peak is 0), ``k*`` the smallest maximiser (the highest level on a tie).
    A thin part that renders opaque is kept when keeping it gains more opaque rays than it adds background ones; a
    faint haze outside the silhouette is left out. A soft model, whose thin parts render half-transparent, still
    gets them from the mask.

``local`` (:data:`LOCAL_LEVEL`, :func:`local_surface`)
    **the half-maximum along each input ray, between the silhouette level and the auto level**: the level at a
    point ``x`` is ``l(x) = clip(0.5 peak(x), L_silhouette, L_auto)`` on the target's rays (the input's mask, else
    the opaque rays) and ``L_auto`` on the others, ``peak(x)`` being the peak density of the input ray through
    ``x`` (the per-pixel peaks of ``silhouette``; ``l`` is bilinear between pixel centres, and pixels outside the
    image read the nearest border pixel). The mesh is the surface ``sigma(x) = l(x)``, extracted as the level 1 of
    ``sigma / l``. Where the input sees background, nothing looser than ``auto`` is extracted. A ray through a
    dense part (a seat; peak at least twice ``auto``'s level) gets ``auto``'s level, from the same rays and
    samples as ``auto``. A ray through a fainter part (a leg) gets that part's own half-maximum, never below the
    silhouette level. So the outline seen from the input camera follows the mask, and the surface along each ray
    is as tight as its half-maximum. :class:`MeshLevel` records ``L_auto`` as ``level`` and ``L_silhouette`` (or
    ``L_auto`` when lower) as ``floor``.

When no ray is opaque the rules fall back to :data:`DEFAULT_THRESHOLD` and :class:`MeshLevel` says so; with a mask,
``local`` also falls back when the mask is empty, and ``silhouette`` only then (its target is the mask, whatever
the opacity).
:data:`DEFAULT_THRESHOLD` (20, NeRF practice being 10-50 for unit-scale scenes): a slab 0.05 thick (5% of a
unit-diagonal SRN object, about a chair leg) at density 20 has opacity ``1 - exp(-20 * 0.05) = 63%``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from jaxtyping import Bool, Float
from torch import Tensor

from depthnerf.data.cameras import Intrinsics, camera_rays, project, world_to_camera
from depthnerf.errors import DepthnerfError

DEFAULT_THRESHOLD = 20.0
"""Fallback density level when no input ray is opaque (see the module docstring)."""
AUTO_LEVEL = "auto"
"""Level rule: half the median peak density over the opaque input rays (:func:`auto_level`)."""
SILHOUETTE_LEVEL = "silhouette"
"""Level rule: the surface whose input-view silhouette best matches the rendered one (:func:`silhouette_level`)."""
LOCAL_LEVEL = "local"
"""Level rule: the half-maximum along each input ray, between the silhouette and the auto level
(:func:`local_surface`)."""
LEVEL_RULES = (AUTO_LEVEL, SILHOUETTE_LEVEL, LOCAL_LEVEL)
"""The per-object level rules, by name."""
AUTO_SAMPLES = 96
"""Uniform samples per input ray for the level rules."""
OPAQUE = 0.5
"""Rays whose opacity exceeds this count as opaque."""

DensityFn = Callable[[Float[Tensor, "N 3"]], Float[Tensor, " N"]]
"""World points -> volume density (a tensor of N values, or N x 1)."""


def query_chunks(fn: Callable[[Tensor], Tensor], points_of: Callable[[int, int], Tensor], total: int,
                 chunk: int, width: int, what: str) -> np.ndarray:
    """Evaluate ``fn`` on ``points_of(start, stop)`` chunk by chunk; returns ``(total, width)`` float32."""
    out = np.empty((total, width), dtype=np.float32)
    with torch.no_grad():
        for start in range(0, total, chunk):
            stop = min(start + chunk, total)
            values = torch.as_tensor(fn(points_of(start, stop))).detach().float().cpu()
            if values.numel() != (stop - start) * width:
                raise DepthnerfError(f"mesh extraction: {what} returned shape {tuple(values.shape)} for "
                                     f"{stop - start} points (expected {stop - start} x {width})")
            out[start:stop] = values.reshape(stop - start, width).numpy()
    if not np.isfinite(out).all():
        raise DepthnerfError(f"mesh extraction: {what} returned {int((~np.isfinite(out)).sum())} non-finite values")
    return out


@dataclass(frozen=True)
class MeshLevel:
    """The density level a mesh was extracted at, and how it was chosen."""

    level: float
    """Marching-cubes density level."""
    rule: str
    """``fixed`` (given), ``auto`` (:func:`auto_level`), ``silhouette`` (:func:`silhouette_level`), ``local``
    (:func:`local_surface`; ``level`` is then its highest level, the auto one) or ``fallback`` (a rule found no
    opaque ray, or an empty mask: the default)."""
    opaque_rays: int = 0
    """Input rays with opacity > :data:`OPAQUE` (rules only)."""
    rays: int = 0
    """Input rays examined (rules only)."""
    iou: float | None = None
    """``silhouette`` and ``local``: IoU of the silhouette level surface's input-view outline with the target rays."""
    target: str = ""
    """``silhouette`` and ``local``: ``mask`` (the input's object mask) or ``opaque`` (the rendered silhouette)."""
    target_rays: int = 0
    """``silhouette`` and ``local``: rays in the target silhouette."""
    floor: float | None = None
    """``local`` only: the silhouette level, the lowest level along any ray (``level`` is the highest)."""

    def describe(self) -> str:
        """One line for records (summary, manifest)."""
        if self.rule == "fixed":
            return f"fixed density level {self.level:g}"
        if self.rule == "fallback" and self.target == "mask":
            return f"silhouette level: the input's mask is empty, fell back to density {self.level:g}"
        if self.rule == "fallback":
            return f"level rule: no opaque input ray (0 of {self.rays}), fell back to density {self.level:g}"
        if self.rule == LOCAL_LEVEL:
            return (f"local level: half the peak density along each input ray, within {self.floor:.4g} (silhouette) "
                    f"- {self.level:.4g} (auto)")
        if self.rule == SILHOUETTE_LEVEL:
            target = "the input's mask" if self.target == "mask" else "the opaque input rays"
            return (f"silhouette level {self.level:.4g}: its input-view silhouette matches {target} "
                    f"({self.target_rays} of {self.rays} rays) with IoU {self.iou:.3f}")
        return (f"auto level {self.level:.4g} = 0.5 x median peak density over {self.opaque_rays} of {self.rays} "
                f"opaque input rays")


def parse_level(text: str) -> float | str:
    """``--mesh-threshold`` value: a positive number or a rule of :data:`LEVEL_RULES`."""
    if text.strip().lower() in LEVEL_RULES:
        return text.strip().lower()
    rules = ", ".join(LEVEL_RULES)
    try:
        value = float(text)
    except ValueError:
        raise DepthnerfError(f"--mesh-threshold: expected a number or one of {rules}, got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise DepthnerfError(f"--mesh-threshold: must be a positive number or one of {rules}, got {text!r}")
    return value


def input_ray_densities(density_fn: DensityFn, c2w: Float[Tensor, "4 4"], intr: Intrinsics, near: float,
                        far: float, samples: int = AUTO_SAMPLES, chunk: int = 65536,
                        device: torch.device | str = "cpu", ray_stride: int = 2
                        ) -> tuple[Float[np.ndarray, " R"], Float[np.ndarray, " R"]]:
    """``(peak, opacity)`` of each ray of every ``ray_stride``-th pixel row and column of the camera
    ``(c2w, intr)``: the largest of ``samples`` bin-midpoint densities between ``near`` and ``far``, and
    ``1 - exp(-sum(max(sigma, 0)) * delta)``, ``delta = (far - near) / samples``."""
    if not 0 < near < far or samples < 1:
        raise DepthnerfError(f"mesh level: need 0 < near < far and samples >= 1, got {near}, {far}, {samples}")
    origins, dirs = camera_rays(torch.as_tensor(c2w, dtype=torch.float32), intr)
    origins, dirs = origins[::ray_stride, ::ray_stride], dirs[::ray_stride, ::ray_stride]
    origins, dirs = origins.reshape(-1, 3).to(device), dirs.reshape(-1, 3).to(device)
    delta = (far - near) / samples
    t = near + (torch.arange(samples, device=device, dtype=torch.float32) + 0.5) * delta  # bin midpoints

    def points_of(start: int, stop: int) -> Tensor:
        flat = torch.arange(start, stop, device=device)
        ray, k = flat // samples, flat % samples
        return origins[ray] + t[k, None] * dirs[ray]

    rays = len(dirs)
    sigma = query_chunks(density_fn, points_of, rays * samples, chunk, 1, "density_fn").reshape(rays, samples)
    opacity = 1.0 - np.exp(-np.clip(sigma, 0, None).astype(np.float64).sum(1) * delta)
    return sigma.max(1).astype(np.float64), opacity


def auto_level(density_fn: DensityFn, c2w: Float[Tensor, "4 4"], intr: Intrinsics, near: float, far: float,
               samples: int = AUTO_SAMPLES, chunk: int = 65536, device: torch.device | str = "cpu",
               ray_stride: int = 2) -> MeshLevel:
    """Half the median peak density over the opaque rays of the camera ``(c2w, intr)`` (module docstring)."""
    peak, opacity = input_ray_densities(density_fn, c2w, intr, near, far, samples, chunk, device, ray_stride)
    opaque = opacity > OPAQUE
    if not opaque.any():
        return MeshLevel(DEFAULT_THRESHOLD, "fallback", 0, len(peak))
    return MeshLevel(half_median(peak, opaque), AUTO_LEVEL, int(opaque.sum()), len(peak))


def half_median(peak: Float[np.ndarray, "*R"], opaque: Bool[np.ndarray, "*R"]) -> float:
    """The ``auto`` level of these rays: half the median peak over the opaque ones (at least one)."""
    return 0.5 * float(np.median(peak[opaque]))


def silhouette_target(mask: Bool[np.ndarray, "H W"] | None, opaque: Bool[np.ndarray, " R"], intr: Intrinsics,
                      ray_stride: int) -> tuple[Bool[np.ndarray, " R"], str]:
    """``(target, name)``: the rays of every ``ray_stride``-th pixel that ``mask`` (the camera's object mask)
    covers, ``"mask"``; without a mask the ``opaque`` rays, ``"opaque"``."""
    if mask is None:
        return opaque, "opaque"
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != (intr.height, intr.width):
        raise DepthnerfError(f"mesh level: mask is {mask.shape[0]}x{mask.shape[1]} "
                             f"but the camera is {intr.height}x{intr.width}")
    return mask[::ray_stride, ::ray_stride].reshape(-1), "mask"


def silhouette_choice(peak: Float[np.ndarray, " R"], opaque: np.ndarray) -> tuple[float, float]:
    """``(level, iou)``: the level whose silhouette ``{peak > level}`` has the largest IoU with ``opaque``
    (module docstring; needs at least one opaque ray)."""
    order = np.argsort(-peak, kind="stable")
    sorted_peak = peak[order]
    tp = np.cumsum(opaque[order])
    kept = np.arange(1, len(peak) + 1)
    iou = tp / (int(opaque.sum()) + kept - tp)
    ends = np.append(sorted_peak[:-1] > sorted_peak[1:], True)  # a level keeps all of a tie or none of it
    positive = sorted_peak > 0  # no positive level keeps a ray whose peak is not
    ends = ends & positive if (ends & positive).any() else ends
    iou = np.where(ends, iou, -1.0)
    k = int(np.argmax(iou))  # first maximiser: the fewest rays kept, the highest level
    below = max(float(sorted_peak[k + 1]), 0.0) if k + 1 < len(peak) else 0.0
    return 0.5 * float(sorted_peak[k] + below), float(iou[k])


def silhouette_level(density_fn: DensityFn, c2w: Float[Tensor, "4 4"], intr: Intrinsics, near: float, far: float,
                     mask: Bool[np.ndarray, "H W"] | None = None, samples: int = AUTO_SAMPLES, chunk: int = 65536,
                     device: torch.device | str = "cpu", ray_stride: int = 1) -> MeshLevel:
    """The level whose input-view silhouette best matches ``mask`` (the camera's ``H x W`` object mask), or the
    opaque rays of ``(c2w, intr)`` without one (module docstring)."""
    peak, opacity = input_ray_densities(density_fn, c2w, intr, near, far, samples, chunk, device, ray_stride)
    opaque = opacity > OPAQUE
    target, name = silhouette_target(mask, opaque, intr, ray_stride)
    if not target.any():
        return MeshLevel(DEFAULT_THRESHOLD, "fallback", int(opaque.sum()), len(peak), None, name, 0)
    level, iou = silhouette_choice(peak, target)
    return MeshLevel(level, SILHOUETTE_LEVEL, int(opaque.sum()), len(peak), iou, name, int(target.sum()))


def local_surface(density_fn: DensityFn, c2w: Float[Tensor, "4 4"], intr: Intrinsics, near: float, far: float,
                  mask: Bool[np.ndarray, "H W"] | None = None, samples: int = AUTO_SAMPLES, chunk: int = 65536,
                  device: torch.device | str = "cpu") -> tuple[MeshLevel, DensityFn, float]:
    """``(level, fn, 1.0)``: the ``local`` rule (module docstring) as the density ``fn = sigma / l`` to extract at
    level 1; the rules' fallback ``(fallback level, density_fn, DEFAULT_THRESHOLD)`` without an opaque ray."""
    peak, opacity = input_ray_densities(density_fn, c2w, intr, near, far, samples, chunk, device, ray_stride=1)
    opaque = opacity > OPAQUE
    target, name = silhouette_target(mask, opaque, intr, 1)
    if not opaque.any() or not target.any():
        return MeshLevel(DEFAULT_THRESHOLD, "fallback", int(opaque.sum()), len(peak)), density_fn, DEFAULT_THRESHOLD
    grid = (intr.height, intr.width)
    auto_peak, auto_opaque = peak.reshape(grid)[::2, ::2], opaque.reshape(grid)[::2, ::2]  # auto_level's rays
    top = half_median(auto_peak, auto_opaque) if auto_opaque.any() else half_median(peak, opaque)
    silhouette, iou = silhouette_choice(peak, target)
    floor = min(silhouette, top)
    level_map = np.where(target, np.clip(0.5 * peak, floor, top), top).reshape(1, 1, *grid)  # background: auto
    levels = torch.as_tensor(level_map, dtype=torch.float32, device=device)
    pose = torch.as_tensor(c2w, dtype=torch.float32, device=device)
    scale = torch.tensor([2.0 / max(intr.width - 1, 1), 2.0 / max(intr.height - 1, 1)], device=device)

    def scaled(points: Tensor) -> Tensor:
        uv = project(world_to_camera(points, pose), intr.focal, (intr.cx, intr.cy))  # pixel (i, j): (u, v) = (j, i)
        at = torch.nn.functional.grid_sample(levels, (uv * scale - 1.0).reshape(1, 1, -1, 2), mode="bilinear",
                                             padding_mode="border", align_corners=True)
        return torch.as_tensor(density_fn(points)).reshape(-1) / at.reshape(-1)

    level = MeshLevel(top, LOCAL_LEVEL, int(opaque.sum()), len(peak), iou, name, int(target.sum()), floor)
    return level, scaled, 1.0


def level_surface(threshold: float | str, density_fn: DensityFn, c2w: Float[Tensor, "4 4"], intr: Intrinsics,
                  near: float, far: float, chunk: int = 65536, device: torch.device | str = "cpu",
                  mask: Bool[np.ndarray, "H W"] | None = None) -> tuple[MeshLevel, DensityFn, float]:
    """``(level, fn, value)``: how ``threshold`` (a number, or a rule resolved along the camera's rays; ``mask``:
    the camera's object mask, the ``silhouette`` and ``local`` rules' target) chose the surface, and the surface
    as the ``value`` level set of ``fn`` (``density_fn`` itself except for ``local``)."""
    if threshold == LOCAL_LEVEL:
        return local_surface(density_fn, c2w, intr, near, far, mask, chunk=chunk, device=device)
    if threshold == AUTO_LEVEL:
        level = auto_level(density_fn, c2w, intr, near, far, chunk=chunk, device=device)
    elif threshold == SILHOUETTE_LEVEL:
        level = silhouette_level(density_fn, c2w, intr, near, far, mask, chunk=chunk, device=device)
    elif isinstance(threshold, int | float) and not isinstance(threshold, bool):
        level = MeshLevel(float(threshold), "fixed")
    else:
        raise DepthnerfError(f"mesh level must be a number or one of {', '.join(LEVEL_RULES)}, got {threshold!r}")
    return level, density_fn, level.level


RULE_TEXTS = (
    (LOCAL_LEVEL, "the local level per object (half the peak density along each input ray, between the silhouette "
                  "and the auto level; per_object.csv mesh_level: the auto level"),
    (SILHOUETTE_LEVEL, "the silhouette level per object (input-view silhouette of the surface matched to the "
                       "input's mask or the opaque input rays"),
    (AUTO_LEVEL, "the auto level per object (0.5 x median peak density over opaque input rays"),
)
"""How :func:`levels_text` names the rule of a set of meshes: the first listed that any of them used (``auto``
for fixed and fallback levels mixed with it)."""


def levels_text(levels: list[MeshLevel], resolution: int) -> str:
    """How several meshes were extracted, for ``summary.json`` ``mesh_status``."""
    grid = f"on a {resolution}-sample frustum grid"
    if not levels:
        return "no mesh"
    if all(lv.rule == "fixed" for lv in levels):
        return f"marching cubes at fixed density level {levels[0].level:g} {grid}"
    rules = {lv.rule for lv in levels}
    rule = next(text for name, text in RULE_TEXTS if name in rules or name == AUTO_LEVEL)
    values = [lv.level for lv in levels]
    fallback = sum(lv.rule == "fallback" for lv in levels)
    return (f"marching cubes {grid} at {rule}; per_object.csv mesh_level): median {float(np.median(values)):.4g}, "
            f"range {min(values):.4g}-{max(values):.4g}"
            + (f"; {fallback} object(s) without an opaque ray fell back to {DEFAULT_THRESHOLD:g}" if fallback else ""))
