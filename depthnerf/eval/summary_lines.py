"""The lines of ``summary.json`` that say in words what an evaluation ran: the protocol, the input views and the
state of the predicted meshes (:mod:`depthnerf.eval.protocol` writes them)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

from depthnerf.data.protocol import INPUT_VIEW, TWO_VIEW_INPUTS, ProtocolViews


class _Scored(Protocol):
    views: ProtocolViews


def input_views_record(results: Sequence[_Scored]) -> list[int] | list[list[int]]:
    """``summary.json`` ``input_views``: the input views every object was conditioned on (primary first), or,
    where objects differ (view 0 of objects with at most 64 views), each distinct list in order."""
    distinct = sorted({r.views.input_views for r in results})
    return list(distinct[0]) if len(distinct) == 1 else [list(v) for v in distinct]


def _inputs_head(inputs: list[tuple[int, ...]], chosen: bool) -> str:
    if inputs == [(INPUT_VIEW,)]:
        return f"SRN protocol: input view {INPUT_VIEW}"
    if inputs == [TWO_VIEW_INPUTS]:
        return f"two-view SRN protocol (pixelNeRF's): input views {TWO_VIEW_INPUTS[0]} and {TWO_VIEW_INPUTS[1]}"
    names = "; ".join(", ".join(map(str, v)) for v in inputs)
    if chosen:  # the same views for every object, as asked
        several = max(map(len, inputs)) > 1
        return (f"SRN-style protocol: input view{'s' if several else ''} {names} (chosen with --input-views"
                f"{'' if several else f'; SRN uses view {INPUT_VIEW}'})")
    if inputs == [(0,)]:
        return f"SRN-style protocol: input view 0 (objects have <= {INPUT_VIEW} views; SRN uses view {INPUT_VIEW})"
    if inputs == [(0,), (INPUT_VIEW,)]:
        return f"SRN protocol: input view {INPUT_VIEW} (view 0 for objects with <= {INPUT_VIEW} views)"
    return f"SRN-style protocol: input view{'s' if max(map(len, inputs)) > 1 else ''} {names}"


def protocol_text(results: Sequence[_Scored], total_objects: int, split: str, category: str, stride: int,
                  eval_res: int, input_res: int, deterministic: bool, skipped: Sequence[str] = (),
                  chosen: bool = False) -> str:
    """One line saying exactly which protocol ran; ``chosen``: the input views were asked for (``--input-views``),
    not the protocol's choice by view count."""
    inputs = sorted({r.views.input_views for r in results})
    others = sorted({r.views.others for r in results})
    scored = sorted({len(r.views.targets) for r in results})
    n_other = "/".join(map(str, others))
    n_scored = "/".join(map(str, scored))
    targets = (f"targets = all other {n_other} views" if stride == 1
               else f"targets = all other {n_other} views with stride {stride} ({n_scored} views)")
    res = f"{eval_res}x{eval_res}"
    if input_res != eval_res:
        plural = "s" if max(map(len, inputs)) > 1 else ""
        res += f" (input view{plural} encoded at the training resolution {input_res}x{input_res})"
    sampling = "deterministic sampling" if deterministic else "random sampling (render.sampler.eval_random)"
    left_out = f" ({', '.join(skipped)} left out: pixelNeRF cannot load it)" if skipped else ""
    return (f"{_inputs_head(inputs, chosen)}, {targets}, {len(results)} of {total_objects} objects of {category}_{split}"
            f"{left_out}, {res}, {sampling}")


def mesh_status(empty: int, meshed: int, total: int) -> str:
    """The head of ``summary.json`` ``mesh_status`` (the extraction levels follow it): ``ok`` with how many of
    ``total`` objects have ``mesh.ply``, unless predicted meshes were empty (then their worst-case Chamfer-L1 and
    F-score are in the means, :mod:`depthnerf.eval.geometry_metrics`), which it says first."""
    have = f"{meshed} of {total} objects have mesh.ply; "
    if empty == 0:
        return f"ok: {have}"
    if empty == meshed:
        return (f"every predicted mesh is empty ({empty} of {meshed}): Chamfer-L1 and F-score are the worst-case "
                f"values, not a measured surface; {have}")
    return f"{empty} of {meshed} predicted meshes empty (worst-case values in the means); {have}"
