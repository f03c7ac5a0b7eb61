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


def check_validation_views(views: Sequence[int], objects: Sequence[tuple[str, int]]) -> None:
    """One line when ``--log.val_views`` cannot be scored as given on the val ``objects`` (``(path, views)``
    pairs): an index past an object's views, or only the object's input view (:func:`protocol_views`), either of
    which validation would have replaced with another view, silently."""
    for path, count in objects:
        past = [v for v in views if v >= count]
        if past:
            raise DepthnerfError(f"--log.val_views {','.join(map(str, views))}: {path} has {count} views (indices "
                                 f"0-{count - 1}), so view {past[0]} does not exist")
        if all(v == protocol_views(count).input_view for v in views):
            raise DepthnerfError(f"--log.val_views {','.join(map(str, views))}: names only {path}'s input view; "
                                 f"name a view to render from it")
