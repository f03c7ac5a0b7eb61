"""Depth stage: frozen monocular depth estimators (relative disparity), their normalisation and cache.

Modules (public API):

- :mod:`~depthnerf.depth.estimators`: the convention (RGB ``[B,3,H,W]`` in [0,1] -> relative disparity
  ``[B,H,W]``, larger = closer), ``DepthEstimator``, ``PriorProvenance``, ``make_estimator(name, checkpoint,
  device)``, ``describe_estimator(name, checkpoint)``, ``oracle_disparity(depth)``; names ``ESTIMATORS``.
- :mod:`~depthnerf.depth.depth_anything`: ``depth-anything-v2`` through transformers (hub id or local dir).
- :mod:`~depthnerf.depth.bundled`: ``bundled``, the small U-Net shipped in ``weights/`` (see its MODEL_CARD.md).
- :mod:`~depthnerf.depth.normalize`: ``normalize_disparity(disp, mask)``, the one network-input normalisation.
- :mod:`~depthnerf.depth.cache`: ``PriorStore.open(data_root, estimator, checkpoint, resolution)``,
  ``store.load(record, views)``, ``store.check(records)``, ``store.provenance``; cache layout and staleness.
- :mod:`~depthnerf.depth.precompute`: ``precompute_priors`` (``depthnerf depth``).
- :mod:`~depthnerf.depth.metrics` / :mod:`~depthnerf.depth.evaluate`: affine-invariant AbsRel / delta<1.25
  (``depthnerf depth-eval``).
"""
