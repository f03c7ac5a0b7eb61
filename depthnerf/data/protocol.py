"""The SRN evaluation protocol's choice of views (pixelNeRF's): view 64 is the input, the other views targets.

Used by ``depthnerf eval``, training validation, the demo and the benchmarks.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from depthnerf.errors import DepthnerfError

INPUT_VIEW = 64
"""The SRN protocol's input view."""
SRN_VIEWS = 251
"""Views per object of the SRN val/test sets."""


@dataclass(frozen=True)
class ProtocolViews:
    """Input and target view indices of one object."""

    input_view: int
    """The view the model is conditioned on."""
    targets: tuple[int, ...]
    """Scored views, in index order."""
    others: int
    """Number of views other than the input (targets before the stride)."""


def protocol_views(num_views: int, stride: int = 1) -> ProtocolViews:
    """View 64 as input (view 0 with <= 64 views), every ``stride``-th other view as a target."""
    if stride < 1:
        raise DepthnerfError(f"--views-stride must be >= 1, got {stride}")
    if num_views < 2:
        raise DepthnerfError(f"an object needs at least 2 views (an input and a target), has {num_views}")
    src = INPUT_VIEW if num_views > INPUT_VIEW else 0
    others = [v for v in range(num_views) if v != src]
    return ProtocolViews(input_view=src, targets=tuple(others[::stride]), others=len(others))


def validation_targets(views: Sequence[int], num_views: int) -> list[int]:
    """The views training validation renders of an object with ``num_views`` views, asked for ``views``
    (``--log.val_views``): those the object has, other than its input view (:func:`protocol_views`); when none is
    left, the view after the input view."""
    src = protocol_views(num_views).input_view
    return [v for v in views if v < num_views and v != src] or [(src + 1) % num_views]


def validation_views_note(views: Sequence[int], objects: Sequence[tuple[str, int]]) -> str | None:
    """A note saying what validation renders instead of ``--log.val_views`` where some val ``objects``
    (``(path, views)`` pairs) lack those views (:func:`validation_targets`; the presets' views are for SRN's
    251-view val objects); None when every object renders them as asked."""
    changed = [(path, count) for path, count in objects if validation_targets(views, count) != list(views)]
    if not changed:
        return None
    path, count = changed[0]
    more = f" (and {len(changed) - 1} more val objects)" if len(changed) > 1 else ""
    rendered = ",".join(map(str, validation_targets(views, count)))
    return (f"note: --log.val_views {','.join(map(str, views))}: {path} has {count} views, input view "
            f"{protocol_views(count).input_view}; validation renders its views {rendered}{more}")
