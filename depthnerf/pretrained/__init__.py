"""Trained models as inference uses them: the inference spec in every checkpoint, weights I/O and loading.

Stage between ``render`` and ``train | eval | reconstruct``: training writes what is here, evaluation and
reconstruction read it, and neither needs the training config.

- :mod:`~depthnerf.pretrained.spec`: :class:`InferenceSpec` (model + render config, prior, z-range, resolution,
  category), its JSON form, and its derivation from checkpoints written before it existed.
- :mod:`~depthnerf.pretrained.weights`: safetensors weights with metadata, atomic writes, strict loading.
- :mod:`~depthnerf.pretrained.load`: ``--checkpoint`` resolution (shipped name, file, folder, run) and
  :func:`load_pretrained`.
- :mod:`~depthnerf.pretrained.card`: the training steps a shipped model card counts (warm-start chains).
- :mod:`~depthnerf.pretrained.official_pixelnerf`: official pixelNeRF weights as this package's baseline network.
- :mod:`~depthnerf.pretrained.recommended`: the shipped checkpoint the demo and the app use per category.
"""
