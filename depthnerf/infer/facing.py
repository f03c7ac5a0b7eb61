"""The object's facing (its mirror plane) estimated from the photo itself, for mirror models (``--facing auto``).

A mirror model reads the input view's features at each point's mirror image in the object's symmetry plane, and
a plane a few degrees off misleads it: with ``cpu-cars-sym-pp`` on 12 test cars, a plane turned 5 degrees from the
true one loses 1.4 dB on the novel views and one turned 10 degrees 3.0 dB, worse than no plane at all
(docs/RESULTS.md, "Facing: how exact the mirror plane must be"). A photo does not say which way its object faces.

The estimate asks the model. Conditioned on each candidate plane, the model renders the input view itself, and the
candidate whose render is closest to the photo wins (the view is the only one whose truth is known). The candidates
are the vertical planes through the origin of reconstruct's frame (+z up, the object at the origin), one per facing
``a`` in [0, 180) degrees (:func:`~depthnerf.data.symmetry.facing_plane`; ``a`` and ``a + 180`` are the same plane),
and "no plane" (the model's no-plane mode, which ``--schedule.mirror_dropout`` trains):

1. ``error(a)`` = the mean squared RGB error between the input view rendered at ``1 / scale`` of its resolution
   and the photo area-averaged to the same size;
2. a coarse pass over :data:`COARSE_STEP`-degree facings, then finer passes of :data:`FINE_STEPS` around the best,
   then the vertex of the parabola through the best and its two 1-degree neighbours;
3. the best facing is kept only if its error is below no plane's (:class:`FacingFit`); otherwise no plane.

Cost: about 30 renders of a quarter-size input view (``scale`` 2), a few seconds on the CPU for the shipped models.

The input view cannot tell a side view from a front view: at both, the plane square to the viewing direction
renders it about as well as the true one, and so does no plane. A checkpoint that carries a facing head
(:mod:`depthnerf.model.facing_head`, ``depthnerf fit-facing``) reads the plane's angle from the encoder's features
instead, and :func:`fit_facing` takes the head's plane as it is: on held-out synthetic objects it is closer to the
true plane than the search, and starting the search there moves it away (docs/RESULTS.md, "A facing head"). The
input-view errors with the head's plane and without a plane are still computed (two renders) for the record, and
the head's :meth:`~depthnerf.model.facing_head.FacingHead.confidence`: where it is low the reading is often tens of
degrees off. Below ``min_confidence`` :func:`fit_facing` chooses no plane; by default (:data:`MIN_CONFIDENCE`) it
never does, because on the shipped chair model, whose head is the one that is unsure, dropping the plane did not
render better than the head's plane even there (docs/RESULTS.md, "When the facing head is unsure").
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from depthnerf.data.symmetry import facing_from_relative, facing_plane
from depthnerf.errors import DepthnerfError
from depthnerf.infer.session import EncodedView, InferenceSession

COARSE_STEP = 10
"""Degrees between the facings of the first pass."""
FINE_STEPS = ((2, 4), (1, 1))
"""Later passes: ``(step, reach)`` tries ``best + k * step`` for ``0 < |k| <= reach`` around the best so far."""
AUTO = "auto"
"""``--facing auto`` / ``ReconstructConfig.facing``: estimate the facing (:func:`fit_facing`)."""
MIN_CONFIDENCE = 0.0
"""Below this confidence of the facing head (:meth:`~depthnerf.model.facing_head.FacingHead.confidence`)
:func:`fit_facing` chooses no plane (``--facing-min-confidence``). 0, the head's plane always: on the shipped chair
model dropping the plane did not render better than the head's plane where the head was unsure (module docstring)."""


@dataclass(frozen=True)
class FacingFit:
    """What :func:`search_facing` found."""

    facing: float | None
    """The chosen facing in degrees, in [0, 180), or None when no plane renders the input view best."""
    best: float
    """The facing whose plane rendered the input view best (chosen or not)."""
    error: float
    """Its error (mean squared RGB error of the input view's render)."""
    none_error: float
    """The error without a plane."""
    errors: dict[float, float]
    """Every facing tried and its error."""
    start: float | None = None
    """Where the search started (:func:`search_facing`'s ``start``), or the facing head's estimate when
    :func:`fit_facing` read it; None: the coarse pass."""
    confidence: float | None = None
    """The facing head's confidence in its estimate (:class:`HeadReading`); None without a head."""

    def as_dict(self) -> dict:
        """JSON-ready (``manifest.json``'s ``facing_fit``)."""
        return {"facing": self.facing, "best": self.best, "error": self.error, "none_error": self.none_error,
                "tried": len(self.errors), "head": self.start, "head_confidence": self.confidence}


def search_facing(error: Callable[[float | None], float], coarse_step: int = COARSE_STEP,
                  fine_steps: tuple[tuple[int, int], ...] = FINE_STEPS, start: float | None = None) -> FacingFit:
    """Minimise ``error(facing)`` over facings in [0, 180) degrees (module docstring, steps 2 and 3); ``error(None)``
    is no plane's. ``start``: begin at this facing instead of the coarse pass (``fine_steps`` then search around
    it). Each facing is evaluated once; angles wrap modulo 180."""
    if coarse_step < 1 or 180 % coarse_step:
        raise DepthnerfError(f"coarse_step must divide 180 degrees, got {coarse_step}")
    errors: dict[float, float] = {}

    def tried(a: float) -> float:
        a = float(a % 180)
        if a not in errors:
            errors[a] = float(error(a))
        return errors[a]

    if start is None:
        for a in range(0, 180, coarse_step):
            tried(a)
    else:
        tried(start)
    best = min(errors, key=errors.get)
    for step, reach in fine_steps:
        for k in range(-reach, reach + 1):
            if k:
                tried(best + k * step)
        best = min(errors, key=errors.get)
    left, right = errors.get((best - 1) % 180), errors.get((best + 1) % 180)
    if left is not None and right is not None and left + right > 2 * errors[best]:
        tried(best + 0.5 * (left - right) / (left + right - 2 * errors[best]))  # the parabola's vertex, |shift| < 1/2
        best = min(errors, key=errors.get)
    none_error = float(error(None))
    chosen = best if errors[best] < none_error else None
    return FacingFit(facing=chosen, best=best, error=errors[best], none_error=none_error, errors=errors,
                     start=None if start is None else float(start % 180))


def facing_error(render: Callable[[tuple[float, float, float, float] | None, int], torch.Tensor],
                 photo: torch.Tensor, scale: int = 2) -> Callable[[float | None], float]:
    """``error(facing)`` for :func:`search_facing`: ``render(plane, side)`` renders the input view at ``side`` pixels
    (``[side, side, 3]``) conditioned on ``plane`` (None: no plane); ``photo`` is the input view ``[3, H, W]`` in
    [0, 1], area-averaged by ``scale``."""
    if scale < 1 or photo.shape[-1] % scale or photo.shape[-2] % scale:
        raise DepthnerfError(f"scale {scale} must divide the input view's size {tuple(photo.shape[-2:])}")
    small = F.avg_pool2d(photo[None].float(), scale)[0].permute(1, 2, 0)
    side = small.shape[0]

    def error(facing: float | None) -> float:
        plane = None if facing is None else facing_plane(facing)
        return float(((render(plane, side).float() - small) ** 2).mean())

    return error


def with_plane(enc, plane: tuple[float, float, float, float] | None):
    """``enc`` (:class:`~depthnerf.model.pixelnerf.EncodedViews` of one object) conditioned on ``plane`` instead
    (None: no plane, the zero row); the features are shared, not recomputed."""
    row = torch.zeros(1, 4) if plane is None else torch.tensor([plane])
    return dataclasses.replace(enc, symmetry_plane=row.to(enc.features.device, enc.features.dtype))


def input_view_error(session: InferenceSession, encoded: EncodedView,
                     scale: int = 2) -> Callable[[float | None], float]:
    """``error(facing)`` of :func:`facing_error` for the object ``encoded`` shows: ``session`` renders its primary
    view conditioned on the facing's plane at ``1 / scale`` of the view's resolution (no gradients)."""
    if not session.model.cfg.mirror:
        raise DepthnerfError(f"{session.name} is not a mirror model: it reads no symmetry plane, so there is no "
                             "facing to estimate")
    photo = encoded.inputs.images[0, 0].float().cpu()

    @torch.no_grad()
    def render(plane: tuple[float, float, float, float] | None, side: int) -> torch.Tensor:
        view = dataclasses.replace(encoded, enc=with_plane(encoded.enc, plane))
        return session.render(view, encoded.pose[None], encoded.intr.resized(side, side)).rgb[0]

    return facing_error(render, photo, scale)


def check_min_confidence(value: object) -> None:
    """One line naming ``--facing-min-confidence`` unless ``value`` is a finite number >= 0."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not (math.isfinite(value) and value >= 0):
        raise DepthnerfError(f"--facing-min-confidence must be a number >= 0, got {value!r}")


@dataclass(frozen=True)
class HeadReading:
    """What a facing head reads from the primary view (:func:`head_facing`)."""

    facing: float
    """The facing in [0, 180) degrees (:func:`~depthnerf.data.symmetry.facing_from_relative` of the head's
    relative angle)."""
    confidence: float
    """:meth:`~depthnerf.model.facing_head.FacingHead.confidence`: about 1 when sure, near 0 when not."""


def head_facing(session: InferenceSession, encoded: EncodedView) -> HeadReading | None:
    """The facing the checkpoint's facing head reads from the primary view's features, and how sure it is; None
    without a head."""
    head = session.pretrained.facing_head
    if head is None:
        return None
    with torch.no_grad():
        psi, confidence = head.read(encoded.enc.features[0, :1])
    return HeadReading(facing_from_relative(float(psi[0]), encoded.pose.double().cpu().numpy()), float(confidence[0]))


def fit_facing(session: InferenceSession, encoded: EncodedView, scale: int = 2,
               min_confidence: float = MIN_CONFIDENCE) -> FacingFit:
    """The facing of the object ``encoded`` shows (module docstring): with a facing head, the head's (whatever
    the input-view errors), or no plane where the head's confidence is below ``min_confidence``; without one,
    :func:`search_facing` over :func:`input_view_error`."""
    check_min_confidence(min_confidence)
    error = input_view_error(session, encoded, scale)
    reading = head_facing(session, encoded)
    if reading is None:
        return search_facing(error)
    head = reading.facing
    with_head, without = error(head), error(None)
    return FacingFit(facing=head if reading.confidence >= min_confidence else None, best=head, error=with_head,
                     none_error=without, errors={head: with_head}, start=head, confidence=reading.confidence)
