"""The SRN evaluation protocol's choice of views (pixelNeRF's): view 64 is the input, the other views targets.

pixelNeRF's two-view SRN protocol conditions on views 64 and 104 (:data:`TWO_VIEW_INPUTS`); any list of input
views can be asked for, and every view that is not an input is a target.

Used by ``depthnerf eval``, training validation, the demo and the benchmarks.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from depthnerf.data.records import ObjectRecord
from depthnerf.errors import DepthnerfError

INPUT_VIEW = 64
"""The SRN protocol's input view."""
TWO_VIEW_INPUTS = (64, 104)
"""pixelNeRF's input views for its two-view SRN results."""
SRN_VIEWS = 251
"""Views per object of the SRN val/test sets."""


@dataclass(frozen=True)
class ProtocolViews:
    """Input and target view indices of one object."""

    input_views: tuple[int, ...]
    """The views the model is conditioned on, the first being the primary view: the camera whose frustum bounds
    the mesh, whose rays set its level and guide the sampler, and whose photo colours it."""
    targets: tuple[int, ...]
    """Scored views, in index order."""
    others: int
    """Number of views other than the inputs (targets before the stride)."""

    @property
    def input_view(self) -> int:
        """The primary input view (the first of :attr:`input_views`)."""
        return self.input_views[0]


def check_input_views(inputs: Sequence[int], flag: str = "--input-views") -> tuple[int, ...]:
    """``inputs`` (given as ``flag``) as given, refused in one line if empty, negative or repeated."""
    inputs = tuple(int(v) for v in inputs)
    if not inputs:
        raise DepthnerfError(f"{flag} needs at least one view index")
    if min(inputs) < 0:
        raise DepthnerfError(f"{flag} must be view indices >= 0, got {' '.join(map(str, inputs))}")
    if len(set(inputs)) != len(inputs):
        raise DepthnerfError(f"{flag} names a view twice: {' '.join(map(str, inputs))}")
    return inputs


def protocol_views(num_views: int, stride: int = 1, inputs: Sequence[int] | None = None) -> ProtocolViews:
    """The input views (None: view 64, view 0 with <= 64 views) and every ``stride``-th other view as a target.
    Explicit ``inputs`` must all exist: an object with fewer views is refused, never given other inputs."""
    if stride < 1:
        raise DepthnerfError(f"--views-stride must be >= 1, got {stride}")
    if inputs is None:
        if num_views < 2:
            raise DepthnerfError(f"an object needs at least 2 views (an input and a target), has {num_views}")
        chosen: tuple[int, ...] = (INPUT_VIEW if num_views > INPUT_VIEW else 0,)
    else:
        chosen = check_input_views(inputs)
        if max(chosen) >= num_views:
            raise DepthnerfError(f"input view {max(chosen)} does not exist: the object has {num_views} views "
                                 f"(0-{num_views - 1})")
        if num_views - len(chosen) < 1:
            raise DepthnerfError(f"an object needs a target view besides its {len(chosen)} input views, has "
                                 f"{num_views} views")
    others = [v for v in range(num_views) if v not in chosen]
    return ProtocolViews(input_views=chosen, targets=tuple(others[::stride]), others=len(others))


def record_views(record: ObjectRecord, stride: int = 1, inputs: Sequence[int] | None = None,
                 flag: str | None = None) -> ProtocolViews:
    """:func:`protocol_views` of ``record``; an object lacking an asked-for view is one line naming its folder (and
    ``flag``, the setting that asked, where given)."""
    try:
        return protocol_views(record.num_views, stride, inputs)
    except DepthnerfError as err:
        raise DepthnerfError(f"{record.path}: {err}{f' ({flag})' if flag else ''}") from None


def validation_targets(views: Sequence[int], num_views: int, inputs: Sequence[int] | None = None) -> list[int]:
    """The views training validation renders of an object with ``num_views`` views, asked for ``views``
    (``--log.val_views``): those the object has, other than its input views (``inputs``, ``--log.val_input_views``;
    None: the protocol's, :func:`protocol_views`); when none is left, the first view after the primary input view
    that is not an input."""
    chosen = protocol_views(num_views, inputs=inputs).input_views
    left = [v for v in views if v < num_views and v not in chosen]
    return left or [next((chosen[0] + k) % num_views for k in range(1, num_views)
                         if (chosen[0] + k) % num_views not in chosen)]


def check_validation_views(views: Sequence[int], objects: Sequence[tuple[str, int]]) -> None:
    """Refuse ``--log.val_views`` naming a view that some val ``objects`` (``(path, views)`` pairs) lack: one line
    naming the flag, the object with the fewest views and how many it has (rendering another view instead would
    score what was not asked for)."""
    if not objects:
        return
    path, count = min(objects, key=lambda o: o[1])
    missing = [v for v in views if v >= count]
    if missing:
        raise DepthnerfError(f"--log.val_views {','.join(map(str, views))}: view {missing[0]} does not exist: val "
                             f"object {path} has {count} views (0-{count - 1}); name views below {count}")


def validation_views_note(views: Sequence[int], objects: Sequence[tuple[str, int]],
                          inputs: Sequence[int] | None = None) -> str | None:
    """A note saying what validation renders instead of ``--log.val_views`` where some val ``objects``
    (``(path, views)`` pairs) lack those views or use one as an input (:func:`validation_targets`; the presets'
    views are for SRN's 251-view val objects); None when every object renders them as asked."""
    changed = [(path, count) for path, count in objects if validation_targets(views, count, inputs) != list(views)]
    if not changed:
        return None
    path, count = changed[0]
    more = f" (and {len(changed) - 1} more val objects)" if len(changed) > 1 else ""
    rendered = ",".join(map(str, validation_targets(views, count, inputs)))
    chosen = protocol_views(count, inputs=inputs).input_views
    said = f"input view {chosen[0]}" if len(chosen) == 1 else f"input views {','.join(map(str, chosen))}"
    return (f"note: --log.val_views {','.join(map(str, views))}: {path} has {count} views, {said}; validation "
            f"renders its views {rendered}{more}")
