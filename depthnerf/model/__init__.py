"""Model stage: image(+depth) encoder, pixel-aligned feature sampling, NeRF MLP, the pixelNeRF module.

Public API: :class:`PixelNeRF` (``encode(SourceViews) -> EncodedViews``, ``field(enc, "coarse"|"fine") ->
FieldFn``), the configs :class:`PixelNeRFConfig`, :class:`EncoderConfig`, :class:`FieldConfig`. Loaded lazily
(PEP 562), so importing :mod:`depthnerf.model.config` (the configs and names the CLI builds its flags from) imports
neither torch nor torchvision.
"""

from __future__ import annotations

from typing import Any

_PUBLIC = {
    "EncoderConfig": "depthnerf.model.config",
    "FieldConfig": "depthnerf.model.config",
    "PixelNeRFConfig": "depthnerf.model.config",
    "EncodedViews": "depthnerf.model.pixelnerf",
    "FieldFn": "depthnerf.model.pixelnerf",
    "PixelNeRF": "depthnerf.model.pixelnerf",
    "SourceViews": "depthnerf.model.pixelnerf",
}

__all__ = sorted(_PUBLIC)


def __getattr__(name: str) -> Any:
    """Lazy access to the public API (PEP 562)."""
    if name in _PUBLIC:
        import importlib

        return getattr(importlib.import_module(_PUBLIC[name]), name)
    raise AttributeError(f"module 'depthnerf.model' has no attribute {name!r}")
