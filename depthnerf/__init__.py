"""depthnerf: depth-aware pixelNeRF for single-image 3D object reconstruction.

Pipeline (one straight line, one sub-package per stage):
``data`` (SRN reader, synthetic generator) -> ``depth`` (monocular priors, cache) -> ``model`` (encoder,
field, pixelNeRF) -> ``render`` (samplers, volume rendering) -> ``train`` -> ``eval`` (metrics, protocol,
mesh, reconstruction) -> ``cli``.
"""

__version__ = "0.1.0"
