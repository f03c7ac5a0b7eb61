"""Inference stage, after ``pretrained/`` and before ``train/ | eval/ | reconstruct/``: one checkpoint and the
caller's overrides resolved once (:class:`InferenceSession`, :mod:`depthnerf.infer.session`)."""

from depthnerf.infer.session import EncodedView, InferenceSession, SessionOptions, resolve_prior

__all__ = ["EncodedView", "InferenceSession", "SessionOptions", "resolve_prior"]
