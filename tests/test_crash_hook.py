"""The ``DEPTHNERF_CRASH_AT`` test hook (``depthnerf.crash_hook``), one rule for training and evaluation: the spec
``[sigterm-|sigint-]STAGE@N`` that tests/test_train.py, tests/test_eval_scale.py and scripts/gpu_check_parts.py
set kills the process at exactly that stage and count."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest

PROBE = "import sys; from depthnerf.crash_hook import crash_point; crash_point(sys.argv[1], int(sys.argv[2]))"


def _exit_code(hook: str | None, stage: str, count: int) -> int:
    env = {k: v for k, v in os.environ.items() if k != "DEPTHNERF_CRASH_AT"}
    if hook is not None:
        env["DEPTHNERF_CRASH_AT"] = hook
    return subprocess.run([sys.executable, "-c", PROBE, stage, str(count)], env=env).returncode


@pytest.mark.parametrize(("hook", "stage", "count", "code"), [
    (None, "state", 4, 0),
    ("state@4", "state", 4, -signal.SIGKILL),
    ("state@4", "state", 3, 0),
    ("best-copied@2", "copied", 2, 0),  # the whole stage name, not its end
    ("eval-object@2", "eval-object", 2, -signal.SIGKILL),
    ("eval-object@2", "object", 2, 0),
    ("step@2", "eval-object", 2, 0),
    ("sigterm-step@2", "step", 2, -signal.SIGTERM),
    ("sigint-validation@3", "validation", 3, -signal.SIGINT),
    ("sigkill-step@2", "step", 2, 0),
])
def test_the_hook_fires_at_exactly_its_stage_and_count(hook, stage, count, code):
    assert _exit_code(hook, stage, count) == code
