"""Depth stage: frozen monocular depth estimators (relative disparity), their normalisation and cache.

Modules (public API):

- :mod:`~depthnerf.depth.prior`: the prior's one road: ``PriorConfig`` (``prior``: ``--depth`` /
  ``--depth-checkpoint``, ``PriorConfig.override`` the one rule for them), ``open_prior(...)`` -> a ``PriorSource``
  (``prior_source``: dataset cache, live estimator, or none) serving raw relative ``disparity``.
- :mod:`~depthnerf.depth.estimators`: the ONE registry of names (``ESTIMATORS``, ``CACHED_ESTIMATORS``,
  ``PHOTO_ESTIMATORS``), ``make_estimator(name, checkpoint, device)``, ``describe_estimator(name, checkpoint)``.
- :mod:`~depthnerf.depth.backend`: the convention (RGB ``[B,3,H,W]`` in [0,1] -> relative disparity ``[B,H,W]``,
  larger = closer), ``DepthEstimator``, ``PriorProvenance``, ``oracle_disparity(depth)``.
- :mod:`~depthnerf.depth.depth_anything`: ``depth-anything-v2`` through transformers (hub id or local dir).
- :mod:`~depthnerf.depth.bundled`: ``bundled``, the small U-Net shipped in ``weights/`` (see its MODEL_CARD.md).
- :mod:`~depthnerf.depth.normalize`: ``normalize_disparity(disp, mask)``, the one network-input normalisation.
- :mod:`~depthnerf.depth.cache`: ``PriorStore.open(data_root, estimator, checkpoint, resolution)``,
  ``store.load(record, views)``, ``store.check(records)``, ``store.provenance``; cache layout and staleness;
  ``as_cached`` (the cache's storage rounding).
- :mod:`~depthnerf.depth.precompute`: ``precompute_priors`` (``depthnerf depth``).
- :mod:`~depthnerf.depth.metrics` / :mod:`~depthnerf.depth.evaluate`: affine-invariant AbsRel / delta<1.25
  (``depthnerf depth-eval``).
"""
