"""Stopping a training run cleanly on SIGTERM (what a cluster sends before it preempts a job) or SIGINT (Ctrl+C).

While the loop runs, :class:`StopRequest` replaces the process's SIGTERM and SIGINT handlers by one that only
records the signal; the loop asks :meth:`StopRequest.requested` after every step, and when a signal came it writes a
checkpoint at that step (the usual atomic write) and returns, so ``--resume`` continues exactly from it. A signal
that arrives during validation abandons the validation (single process; with several ranks the other ranks wait for
rank 0 in the next step's gradient reduction, so rank 0 finishes it) and the checkpoint of the step is written all
the same, with that validation due: the resume runs it first (:mod:`depthnerf.train.loop`). A second Ctrl+C while
the checkpoint is being written raises ``KeyboardInterrupt`` (the write is atomic: the run keeps its previous
checkpoint). With several ranks (torchrun), every rank reports whether it saw a signal after each step (one MAX
all-reduce of one number, over gloo), so all ranks stop at the same step and none is left waiting in a collective.

Exit status of ``depthnerf train`` after such a stop: ``128 + signal number`` (130 for SIGINT, 143 for SIGTERM).
Handlers are installed only in the main thread (Python allows no other); the previous handlers come back when
the loop ends.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator
from types import FrameType

import torch

from depthnerf.distributed import DistInfo

STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)
"""Signals that stop training with a checkpoint."""


class ValidationInterrupted(Exception):
    """Raised inside an interruptible validation when a stop signal arrives (caught by the loop)."""


def exit_code(signum: int) -> int:
    """The shell's status of a process ended by ``signum``: ``128 + signum`` (SIGINT 130, SIGTERM 143)."""
    return 128 + int(signum)


def signal_name(signum: int) -> str:
    """``SIGTERM``, ``SIGINT``, ..."""
    return signal.Signals(signum).name


class StopRequest:
    """Records SIGTERM / SIGINT while the training loop runs (a context manager; module docstring)."""

    def __init__(self, info: DistInfo) -> None:
        self.info = info
        self.signum: int | None = None
        """The first stop signal received by this process (None: none yet)."""
        self._interruptible = False
        self._previous: dict[int, object] = {}
        self._group = None

    def __enter__(self) -> StopRequest:
        if self.info.world > 1 and torch.distributed.is_initialized():
            # a CPU flag needs a CPU backend; every rank creates the group at the same point of the loop
            gloo = torch.distributed.get_backend() == "gloo"
            self._group = None if gloo else torch.distributed.new_group(backend="gloo")
        if threading.current_thread() is threading.main_thread():
            for sig in STOP_SIGNALS:
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler if handler is not None else signal.SIG_DFL)
        self._previous.clear()

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self.signum is not None and signum == signal.SIGINT:
            raise KeyboardInterrupt  # a second Ctrl+C: stop now
        if self.signum is None:
            self.signum = signum
        if self._interruptible:
            self._interruptible = False
            raise ValidationInterrupted

    @contextlib.contextmanager
    def interruptible(self) -> Iterator[None]:
        """A block (validation) that a stop signal abandons with :class:`ValidationInterrupted` (single process
        only; see the module docstring). Raises at once if a signal already came."""
        if self.signum is not None:
            raise ValidationInterrupted
        self._interruptible = self.info.world == 1
        try:
            yield
        finally:
            self._interruptible = False

    def requested(self) -> bool:
        """Whether any rank received a stop signal (a collective when there are several ranks: all call it)."""
        if self.info.world == 1 or not torch.distributed.is_initialized():
            return self.signum is not None
        flag = torch.tensor([0 if self.signum is None else int(self.signum)], dtype=torch.int64)
        torch.distributed.all_reduce(flag, op=torch.distributed.ReduceOp.MAX, group=self._group)
        if flag.item() and self.signum is None:
            self.signum = int(flag.item())
        return bool(flag.item())
