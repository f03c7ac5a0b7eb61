"""Model stage: image(+depth) encoder, pixel-aligned feature sampling, NeRF MLP, the pixelNeRF module.

Public API: :class:`PixelNeRF` (``encode(SourceViews) -> EncodedViews``, ``field(enc, "coarse"|"fine") ->
FieldFn``), the configs :class:`PixelNeRFConfig`, :class:`EncoderConfig`, :class:`FieldConfig`.
"""

from depthnerf.model.config import EncoderConfig, FieldConfig, PixelNeRFConfig
from depthnerf.model.pixelnerf import EncodedViews, FieldFn, PixelNeRF, SourceViews

__all__ = ["EncodedViews", "EncoderConfig", "FieldConfig", "FieldFn", "PixelNeRF", "PixelNeRFConfig", "SourceViews"]
