"""pytest plugin of scripts/gpu_check.py: a time budget and a per-test record written as tests finish.

Loaded with ``-p gpu_check_pytest`` (the driver copies this file into a folder of its own and puts that folder on
PYTHONPATH, so the scripts folder itself never is). Environment:

- ``GPU_CHECK_DEADLINE``: Unix time; a test whose setup starts after it is skipped with :data:`BUDGET_REASON`
  (so pytest ends on its own, with its summary, when the budget is spent; the test running then finishes).
- ``GPU_CHECK_REPORT``: a JSON-lines file. One line ``{"collected": N, "ids": [...]}`` once collection is done,
  then one line
  per test phase (setup / call / teardown) that failed, was skipped, or is a call: ``nodeid``, ``when``,
  ``outcome``, ``duration``, ``message`` (a failure's last lines, a skip's reason), ``xfail``. Lines are appended
  and flushed as reports arrive, so a run killed from outside still leaves what finished. Under pytest-xdist only
  the controller writes (workers' reports reach it).
"""

from __future__ import annotations

import json
import os
import time

import pytest

BUDGET_REASON = "gpu_check: time budget spent"

_config = None


def _is_worker(config) -> bool:
    return hasattr(config, "workerinput")


def _write(line: dict) -> None:
    path = os.environ.get("GPU_CHECK_REPORT")
    if not path or _config is None or _is_worker(_config):
        return
    with open(path, "a") as f:
        f.write(json.dumps(line) + "\n")
        f.flush()


def pytest_configure(config) -> None:
    global _config
    _config = config


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item) -> None:
    deadline = os.environ.get("GPU_CHECK_DEADLINE")
    if deadline and time.time() > float(deadline):
        pytest.skip(BUDGET_REASON)


def pytest_collection_finish(session) -> None:
    _write({"collected": len(session.items), "ids": [item.nodeid for item in session.items]})


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_node_collection_finished(node, ids) -> None:
    global _collected_once
    if not globals().get("_collected_once"):
        _collected_once = True
        _write({"collected": len(ids), "ids": list(ids)})


def _message(report) -> str:
    if report.skipped and isinstance(report.longrepr, tuple):
        return str(report.longrepr[2]).removeprefix("Skipped: ")
    text = str(report.longrepr or "")
    lines = [line for line in text.splitlines() if line.strip()]
    return "\n".join(lines[-6:])[-600:]


def pytest_runtest_logreport(report) -> None:
    if report.when != "call" and report.passed:
        return
    _write({"nodeid": report.nodeid, "when": report.when, "outcome": report.outcome,
            "duration": round(report.duration, 3), "message": _message(report) if not report.passed else "",
            "xfail": hasattr(report, "wasxfail")})  # its value is the reason, often empty
