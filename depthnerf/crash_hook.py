"""The crash test hook, one rule for training and evaluation: ``DEPTHNERF_CRASH_AT=STAGE@N`` in the environment
makes the process SIGKILL itself at the :func:`crash_point` of that stage and count, so a test can kill a run at
an exact point of its work instead of racing a timer; ``sigterm-STAGE@N`` / ``sigint-STAGE@N`` send it SIGTERM /
SIGINT there instead (training's clean stop, :mod:`depthnerf.train.stop`). Without the variable every crash point
is a no-op.

Stages: the points of a checkpoint write (:data:`depthnerf.train.checkpoint.CRASH_STAGES`, ``N`` the step), the
training loop's ``step`` and ``validation`` (``N`` the step), and evaluation's ``eval-object``
(:data:`depthnerf.eval.shards.CRASH_STAGE`, ``N`` the objects a process has written).
"""

from __future__ import annotations

import os
import signal

CRASH_ENV = "DEPTHNERF_CRASH_AT"
"""The environment variable of the hook."""
SIGNAL_HOOKS = {"sigterm": signal.SIGTERM, "sigint": signal.SIGINT}
"""``DEPTHNERF_CRASH_AT=<name>-STAGE@N``: the signal sent instead of SIGKILL."""


def crash_point(stage: str, count: int) -> None:
    """SIGKILL this process if ``DEPTHNERF_CRASH_AT`` is ``stage@count``, send it SIGTERM / SIGINT if it is
    ``sigterm-stage@count`` / ``sigint-stage@count`` (test hook; a no-op otherwise)."""
    hook = os.environ.get(CRASH_ENV)
    if not hook or not hook.endswith(f"{stage}@{count}"):
        return
    if hook == f"{stage}@{count}":
        os.kill(os.getpid(), signal.SIGKILL)
    for name, sig in SIGNAL_HOOKS.items():
        if hook == f"{name}-{stage}@{count}":
            os.kill(os.getpid(), sig)
