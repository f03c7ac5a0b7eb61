"""What the training loop needs from validation (structural types; the implementation is
:func:`depthnerf.eval.validation.validate`, which ``depthnerf train`` passes in, so ``train`` never imports ``eval``)
and the loop's validation phase (:class:`ValidationPhase`: which steps validate, one validation as its own phase,
and on resume the validation of the checkpoint's step that a stop signal skipped or abandoned).
"""

from __future__ import annotations

import dataclasses
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch
from tqdm import tqdm

from depthnerf.crash_hook import crash_point
from depthnerf.data.records import ObjectRecord
from depthnerf.depth.prior import PriorSource
from depthnerf.distributed import DistInfo
from depthnerf.model.pixelnerf import PixelNeRF
from depthnerf.pretrained.spec import InferenceSpec
from depthnerf.train import checkpoint as ckpt
from depthnerf.train import memory
from depthnerf.train.config import TrainConfig
from depthnerf.train.run_log import RunLog
from depthnerf.train.stop import StopRequest, ValidationInterrupted


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


@dataclasses.dataclass(frozen=True)
class ValidationPhase:
    """The training loop's validation: every ``log.val_every`` steps and at the last step, on rank 0, scored on
    ``records`` and logged."""

    validate: Validator | None
    """The validator (None: no validation)."""
    records: Sequence[ObjectRecord]
    """The val objects (rank 0's; none on the other ranks)."""
    prior_source: PriorSource
    """The run's depth prior."""
    spec: InferenceSpec
    """The run's inference spec (resolution, z-range, render settings)."""
    cfg: TrainConfig
    """The run's config."""
    info: DistInfo
    """This process's rank, world size and device."""
    plane: tuple[float, ...] | None
    """The objects' mirror plane (mirror models), else None."""
    progress: bool
    """Show the validation's progress bar."""

    @property
    def enabled(self) -> bool:
        """Whether the run validates at all (the same on every rank)."""
        return self.validate is not None and self.cfg.log.val_every > 0

    def due(self, step: int) -> bool:
        """Whether the run validates after step ``step`` (the same on every rank)."""
        return self.enabled and (step % self.cfg.log.val_every == 0 or step == self.cfg.schedule.max_steps)

    def score(self, stop: StopRequest, model: PixelNeRF, step: int, log: RunLog,
              checkpoint: Path | None) -> ValidationScores | None:
        """Validate the model after step ``step`` (rank 0) and log the scores; None when a stop signal abandoned it
        (:meth:`StopRequest.interruptible`). Its own progress bar over the val objects; out of memory, one line
        (``checkpoint``: the run's last)."""
        cfg, info = self.cfg, self.info
        try:
            with tqdm(total=len(self.records), desc=f"validate (step {step})", unit="object", leave=False,
                      position=1, dynamic_ncols=True, disable=not self.progress) as vbar, stop.interruptible(), \
                    memory.one_line_out_of_memory(info, lambda: memory.in_validation(cfg, step, checkpoint)):
                crash_point("validation", step)
                res = self.validate(model, self.records, self.prior_source, cfg.log.val_views, self.spec,
                                    cfg.log.render_chunk, info.device, progress=vbar.update,
                                    symmetry_plane=self.plane, inputs=cfg.log.val_input_views or None)
        except ValidationInterrupted:
            return None
        log.log(step, {"val_psnr": res.psnr, "val_ssim": res.ssim}, prefix="val")
        log.images(step, res.images)
        return res

    def due_on_resume(self, stop: StopRequest, model: PixelNeRF, state: ckpt.TrainingState, log: RunLog,
                      checkpoint: Path) -> tuple[float, int | None, bool]:
        """Rank 0, on resume from ``checkpoint`` (of ``state``, whose validation is due): validate its step, record
        that in the checkpoint's state (:func:`depthnerf.train.checkpoint.rewrite_state`) and, when it is the best
        so far, in ``best/``, as the uninterrupted run did; returns the best PSNR and its step, and whether the
        validation is still due (a stop signal abandoned it again)."""
        print(f"validating step {state.step} first (a stop signal came before its validation ended)",
              file=sys.stderr, flush=True)
        res = self.score(stop, model, state.step, log, checkpoint)
        if res is None:
            return state.best_psnr, state.best_step, True
        improved = res.psnr > state.best_psnr
        best, best_step = (res.psnr, state.step) if improved else (state.best_psnr, state.best_step)
        ckpt.rewrite_state(checkpoint, dataclasses.replace(state, best_psnr=best, best_step=best_step,
                                                           validation_due=False))
        if improved:
            ckpt.mark_best(checkpoint.parent, checkpoint)
        return best, best_step, False
