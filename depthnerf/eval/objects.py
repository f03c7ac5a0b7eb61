"""One object as every evaluation path prepares it: SRN protocol views, the input view conditioned and encoded.

``depthnerf eval`` (:mod:`depthnerf.eval.protocol`), the demo, the guided-sampling benchmark and the mesh
diagnostics go through :func:`prepare_object`, so an object is conditioned the same way everywhere: view
:data:`~depthnerf.data.protocol.INPUT_VIEW` loaded at the training resolution (with its ground-truth depth when
the prior source reads it), conditioned on the session's prior source and encoded once
(:meth:`InferenceSession.encode_views <depthnerf.infer.session.InferenceSession.encode_views>`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from depthnerf.data.protocol import INPUT_VIEW, SRN_VIEWS, TWO_VIEW_INPUTS, ProtocolViews, protocol_views
from depthnerf.data.srn import ObjectRecord, ObjectViews
from depthnerf.infer.session import EncodedView, InferenceSession

__all__ = ["INPUT_VIEW", "SRN_VIEWS", "TWO_VIEW_INPUTS", "ProtocolViews", "protocol_views", "PreparedObject",
           "prepare_object"]


@dataclass
class PreparedObject:
    """One object as every evaluation path prepares it: the input view encoded once, the target views loaded."""

    views: ProtocolViews
    """Input and target view indices."""
    source: ObjectViews
    """The input views at the training resolution."""
    targets: ObjectViews
    """The target views at the evaluated resolution."""
    encoded: EncodedView
    """The input views conditioned on their prior and encoded (``encoded.disparity``: the primary view's raw
    disparity)."""


@torch.no_grad()
def prepare_object(session: InferenceSession, record: ObjectRecord, views: ProtocolViews,
                   eval_res: int | None = None, symmetry_plane: Sequence[float] | None = None) -> PreparedObject:
    """Load the input views at the training resolution, condition them on the session's prior source (and, for
    mirror models, ``symmetry_plane``: :meth:`InferenceSession.dataset_symmetry`) and encode them; load the targets
    at ``eval_res`` (None: the training resolution). Both are read with the session's pixel centre."""
    res = session.spec.resolution
    src = session.load_views(record, list(views.input_views), res, with_depth=session.prior_source.needs_depths)
    tgt = session.load_views(record, list(views.targets), eval_res or res)
    return PreparedObject(views=views, source=src, targets=tgt,
                          encoded=session.encode_views(src, symmetry_plane=symmetry_plane))
