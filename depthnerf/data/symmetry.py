"""Mirror symmetry of the objects: the plane convention, reflections, and where a dataset's plane comes from.

Convention (stated here once). A symmetry plane is four numbers ``(nx, ny, nz, d)`` in the WORLD frame of the
object's cameras: the points ``x`` with ``n . x = d`` for a unit normal ``n``. The mirror image of a point is
``x' = x - 2 (n . x - d) n`` and of a direction ``v' = v - 2 (n . v) n``. The all-zero plane means "no plane"
(the reflection formulas then return their input unchanged), which is how a batch mixes objects with and without
one.

Where a dataset's plane comes from (:func:`dataset_plane`):

- a dataset card (``<root>/<category>_card.json``, written by ``depthnerf synth``) that states ``"mirror_plane"``,
  or whose ``"objects"`` entry names the objects' ``front`` and ``up`` axes and ``centre``: the plane through the
  centre whose normal is the left-right axis ``up x front`` (synthetic data: front +x, up +z, so ``y = 0``);
- otherwise ShapeNet's left-right plane, :data:`SHAPENET_PLANE`: ShapeNetCore objects are centred with the front
  along -Z and up along +Y, so the left-right axis is X; SRN's renders keep X as the left-right axis (their
  Blender import turns -Z forward / +Y up into Blender's frame without touching X), so the plane is ``x = 0``;
- ``--data.symmetry_plane nx ny nz d`` overrides both (data with other axes).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from jaxtyping import Float
from torch import Tensor

from depthnerf.data.card import card_path, read_dataset_card
from depthnerf.errors import DepthnerfError

SHAPENET_PLANE: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
"""ShapeNet's (and SRN's) left-right symmetry plane ``x = 0`` (see the module docstring)."""

_AXES = {"+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0), "+z": (0, 0, 1), "-z": (0, 0, -1)}


def normalized_plane(plane: tuple[float, ...] | list[float], where: str) -> tuple[float, float, float, float]:
    """``plane`` with a unit normal (d scaled alike); a one-line error naming ``where`` for a bad one."""
    try:
        values = [float(v) for v in plane]
    except (TypeError, ValueError):  # not a list, or an entry that is not a number
        values = []
    norm = float(np.linalg.norm(values[:3])) if len(values) == 4 else 0.0
    if len(values) != 4 or not np.all(np.isfinite(values)) or norm < 1e-8:
        raise DepthnerfError(f"{where}: a symmetry plane is 4 finite numbers nx ny nz d with a non-zero normal, "
                             f"got {plane}")
    return (values[0] / norm, values[1] / norm, values[2] / norm, values[3] / norm)


def plane_from_card(card: dict, where: str) -> tuple[float, float, float, float] | None:
    """The plane a dataset card states (``mirror_plane``, or ``objects.front/up/centre``); None if it says none."""
    if "mirror_plane" in card:
        return normalized_plane(card["mirror_plane"], f"{where} mirror_plane")
    objects = card.get("objects") or {}
    if not isinstance(objects, dict):
        raise DepthnerfError(f"{where}: objects must be a JSON object (front, up, centre), got {objects!r}")
    front, up = objects.get("front"), objects.get("up")
    if front is None or up is None:
        return None
    if not isinstance(front, str) or not isinstance(up, str) or front not in _AXES or up not in _AXES:
        raise DepthnerfError(f"{where}: objects.front / objects.up must be one of {sorted(_AXES)}, "
                             f"got {front!r} / {up!r}")
    left = np.cross(np.array(_AXES[up], float), np.array(_AXES[front], float))
    if not np.any(left):
        raise DepthnerfError(f"{where}: objects.front {front} and objects.up {up} are parallel")
    centre = objects.get("centre", (0.0, 0.0, 0.0))
    try:
        centre = np.asarray(centre, dtype=float)
    except (TypeError, ValueError):
        centre = np.zeros(0)
    if centre.shape != (3,) or not np.all(np.isfinite(centre)):
        raise DepthnerfError(f"{where}: objects.centre must be 3 finite numbers x y z, got "
                             f"{objects.get('centre')!r}")
    return normalized_plane((*left.tolist(), float(left @ centre)), where)


def dataset_plane(root: str | Path, category: str, override: tuple[float, ...] | None = None,
                  flag: str = "--data.symmetry_plane") -> tuple[tuple[float, float, float, float], str]:
    """The symmetry plane of a dataset and where it came from (see the module docstring); ``flag`` names the
    setting that gave ``override`` (in its errors and as its source)."""
    if override is not None:
        return normalized_plane(override, flag), flag
    card = read_dataset_card(root, category)
    if card is not None:
        plane = plane_from_card(card, str(card_path(root, category)))
        if plane is not None:
            return plane, f"dataset card {card_path(root, category).name}"
    return SHAPENET_PLANE, "ShapeNet's left-right plane x = 0 (no dataset card states one)"


def reflect_points(points: Float[Tensor, "B N 3"], plane: Float[Tensor, "B 4"]) -> Float[Tensor, "B N 3"]:
    """Mirror images ``x - 2 (n . x - d) n`` of each object's points in its plane (unchanged for a zero plane)."""
    n, d = plane[:, None, :3], plane[:, None, 3:]
    return points - 2.0 * ((points * n).sum(-1, keepdim=True) - d) * n


def reflect_dirs(dirs: Float[Tensor, "B N 3"], plane: Float[Tensor, "B 4"]) -> Float[Tensor, "B N 3"]:
    """Mirror images ``v - 2 (n . v) n`` of directions (unchanged for a zero plane)."""
    n = plane[:, None, :3]
    return dirs - 2.0 * (dirs * n).sum(-1, keepdim=True) * n


def has_plane(plane: Float[Tensor, "B 4"]) -> Float[Tensor, " B"]:
    """1.0 for objects with a plane (non-zero normal), 0.0 for the "no plane" zero row."""
    return (plane[:, :3].abs().sum(-1) > 0).to(plane.dtype)


def facing_plane(facing_deg: float) -> tuple[float, float, float, float]:
    """The plane of an object at the origin whose front points ``facing_deg`` degrees from the direction towards
    the camera, turning towards the image's right (0: faces the camera, 90: faces right), for a camera at azimuth
    0 of a +z-up world (:mod:`depthnerf.reconstruct.orbit`): front ``(cos a, sin a, 0)``, normal ``(-sin a, cos a,
    0)``. Facing ``a`` and ``a + 180`` give the same plane."""
    a = np.radians(float(facing_deg))
    return normalized_plane((round(-np.sin(a), 12), round(np.cos(a), 12), 0.0, 0.0), "facing")


def relative_facing(plane: tuple[float, ...] | np.ndarray, c2w: np.ndarray) -> float:
    """The angle ``psi`` in [0, 180) degrees of a vertical plane's normal seen from a camera without roll: measured
    from the camera's horizontal viewing direction, turning towards the image's right (0: the plane faces the
    camera square on, as at a side view; 90: it contains the viewing direction, as at a front view). With ``n`` the
    unit normal and ``r``, ``f`` the camera's right and forward axes (``c2w[:3, 0]``, ``c2w[:3, 2]``, OpenCV axes),
    both ``n`` and ``r`` are horizontal, so ``sin psi = n . r`` and ``cos psi = sign(n . f) sqrt(1 - (n . r)^2)``:
    no up axis is needed. The inverse, for a +z-up world, is :func:`facing_from_relative`."""
    n = np.asarray(plane[:3], dtype=np.float64)
    n = n / np.linalg.norm(n)
    c2w = np.asarray(c2w, dtype=np.float64)
    right = c2w[:3, 0] / np.linalg.norm(c2w[:3, 0])
    sin_psi = float(n @ right)
    cos_psi = float(np.copysign(np.linalg.norm(n - sin_psi * right), n @ c2w[:3, 2]))  # no cancellation near 90
    return float(np.degrees(np.arctan2(sin_psi, cos_psi)) % 180.0)


def facing_from_relative(psi_deg: float, c2w: np.ndarray) -> float:
    """The facing ``a`` in [0, 180) (:func:`facing_plane`, a +z-up world) of the vertical plane whose normal is at
    ``psi_deg`` from the camera ``c2w``'s horizontal viewing direction ``u`` (:func:`relative_facing`): normal
    ``n = cos psi u + sin psi (u x z)``, and ``a = atan2(-n_x, n_y)``. For the camera at azimuth 0 of
    :func:`facing_plane` (looking along -x) this is ``a = 90 - psi``."""
    forward = np.asarray(c2w, dtype=np.float64)[:3, 2].copy()
    forward[2] = 0.0
    length = np.linalg.norm(forward)
    if length < 1e-9:
        raise DepthnerfError("the camera looks straight down or up: its horizontal viewing direction is undefined")
    u = forward / length
    right = np.cross(u, (0.0, 0.0, 1.0))
    psi = np.radians(float(psi_deg))
    n = np.cos(psi) * u + np.sin(psi) * right
    return float(np.degrees(np.arctan2(-n[0], n[1])) % 180.0)
