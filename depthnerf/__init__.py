"""depthnerf: depth-aware pixelNeRF for single-image 3D object reconstruction.

Pipeline (one straight line, one sub-package per stage):
``data`` (SRN reader, dataset cards, synthetic generator) -> ``depth`` (monocular priors, prior sources, cache) ->
``model`` (conditioning, encoder, field, pixelNeRF) -> ``render`` (samplers, volume rendering, guided sampling,
meshes, device policy) -> ``pretrained`` (inference spec, weights, loading) -> ``infer`` (the inference session)
-> ``train`` | ``eval`` (SRN protocol, metrics) | ``reconstruct`` (one photo in) -> ``commands`` (the CLI),
``app`` and ``demo``. See docs/architecture.md.

Importing the package first sets the process-wide CPU settings the CLI uses (OpenMP wait policy PASSIVE unless
``OMP_WAIT_POLICY`` is set, glibc malloc keeps freed memory; :mod:`depthnerf.cpu_runtime`), before anything
imports torch; ``DEPTHNERF_PROCESS_DEFAULTS=0`` turns that off.

Public API (imported lazily, so ``import depthnerf`` stays cheap)::

    from depthnerf import Reconstructor
    rec = Reconstructor.from_pretrained("cpu-cars-depth")     # device="cuda": bf16, large ray chunks
    result = rec.reconstruct("car.png")
    rec.save(result, "out/")

``InferenceSession`` / ``SessionOptions`` (:mod:`depthnerf.infer.session`): a checkpoint and overrides resolved
once, what ``Reconstructor``, ``depthnerf eval``, the demo and the app run on.
"""

from __future__ import annotations

from typing import Any

from depthnerf.cpu_runtime import configure_process as _configure_process

_configure_process()  # before torch is imported (OpenMP reads its wait policy once); never overrides the user

__version__ = "0.1.0"

_PUBLIC = {
    "Reconstructor": "depthnerf.reconstruct.reconstructor",
    "ReconstructConfig": "depthnerf.reconstruct.reconstructor",
    "Reconstruction": "depthnerf.reconstruct.result",
    "prepare_photo": "depthnerf.reconstruct.photo",
    "BackgroundRemover": "depthnerf.reconstruct.background",
    "InferenceSession": "depthnerf.infer.session",
    "SessionOptions": "depthnerf.infer.session",
}

__all__ = [*_PUBLIC, "__version__"]


def __getattr__(name: str) -> Any:
    """Lazy access to the public API (PEP 562)."""
    if name in _PUBLIC:
        import importlib

        return getattr(importlib.import_module(_PUBLIC[name]), name)
    raise AttributeError(f"module 'depthnerf' has no attribute {name!r}")
