"""Model stage: image(+depth) encoder, pixel-aligned feature sampling, NeRF MLP, the pixelNeRF module."""
