"""What the training loop needs from validation (structural types; the implementation is
:func:`depthnerf.eval.validation.validate`, which ``depthnerf train`` passes in, so ``train`` never imports ``eval``)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, Protocol

import numpy as np
import torch

from depthnerf.data.records import ObjectRecord
from depthnerf.depth.prior import PriorSource
from depthnerf.model.pixelnerf import PixelNeRF
from depthnerf.pretrained.spec import InferenceSpec


class ValidationScores(Protocol):
    """Mean metrics over the validation objects and images of the first one for TensorBoard."""

    psnr: float
    ssim: float
    images: dict[str, np.ndarray]


class Validator(Protocol):
    """``validate(model, records, prior_source, views, spec, chunk, device, progress=None, symmetry_plane=None,
    inputs=None)``: render ``views`` of each record from its input views (``inputs``; None: the protocol's)
    (conditioned on ``prior_source`` and, for mirror models, the symmetry plane) and score them; ``progress(1)``
    after each record (the loop's validation progress bar)."""

    def __call__(self, model: PixelNeRF, records: Sequence[ObjectRecord], prior_source: PriorSource,
                 views: Sequence[int], spec: InferenceSpec, chunk: int, device: torch.device,
                 progress: Callable[[int], Any] | None = None,
                 symmetry_plane: Sequence[float] | None = None,
                 inputs: Sequence[int] | None = None) -> ValidationScores: ...
