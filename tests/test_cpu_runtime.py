"""The process-wide CPU settings of ``depthnerf.cpu_runtime`` (each checked in a fresh interpreter)."""

from __future__ import annotations

import os
import platform
import subprocess
import sys
from pathlib import Path

import pytest

from depthnerf.cpu_runtime import OMP_WAIT_POLICY, configure_process, keep_freed_memory, set_omp_wait_policy

ROOT = Path(__file__).resolve().parents[1]
GLIBC = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"

# Page faults of a 64 MiB allocation made, touched and freed three times in a row.
FAULT_PROBE = """
import resource, sys
from depthnerf.cpu_runtime import keep_freed_memory
applied = keep_freed_memory() if sys.argv[1] == "tune" else False
faults = []
for _ in range(3):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    block = bytearray(64 << 20)
    del block
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
print(applied, *faults)
"""


def probe(mode: str) -> tuple[bool, list[int]]:
    env = {**os.environ, "DEPTHNERF_PROCESS_DEFAULTS": "0"}  # importing the package would tune malloc already
    out = subprocess.run([sys.executable, "-c", FAULT_PROBE, mode], capture_output=True, text=True, check=True,
                         env=env)
    applied, *faults = out.stdout.split()
    return applied == "True", [int(f) for f in faults]


@pytest.mark.skipif(not GLIBC, reason="the malloc tuning applies to glibc only")
def test_keep_freed_memory_reuses_pages():
    pages = (64 << 20) // 4096
    applied, default = probe("default")
    assert not applied and min(default[1:]) > pages // 2  # glibc unmaps and page-faults every big block anew
    applied, tuned = probe("tune")
    assert applied and max(tuned[1:]) < pages // 100  # the freed block is reused without faults


def test_opt_out_and_wait_policy():
    assert keep_freed_memory({"DEPTHNERF_MALLOC_TUNING": "0"}) is False
    env = {}
    set_omp_wait_policy(env)
    assert env == {"OMP_WAIT_POLICY": OMP_WAIT_POLICY}
    env = {"OMP_WAIT_POLICY": "ACTIVE"}
    set_omp_wait_policy(env)
    assert env["OMP_WAIT_POLICY"] == "ACTIVE"


IMPORT_PROBE = """
import os, sys
import depthnerf
print(os.environ.get("OMP_WAIT_POLICY"), "torch" in sys.modules)
"""


@pytest.mark.parametrize(("preset", "expected"), [
    ({}, "PASSIVE"),  # the API configures itself
    ({"OMP_WAIT_POLICY": "ACTIVE"}, "ACTIVE"),  # an explicit setting is kept
    ({"DEPTHNERF_PROCESS_DEFAULTS": "0"}, "None"),  # opted out: nothing changed
])
def test_importing_the_package_sets_the_defaults_before_torch(preset, expected):
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "DEPTHNERF_PROCESS_DEFAULTS")}
    out = subprocess.run([sys.executable, "-c", IMPORT_PROBE], capture_output=True, text=True, check=True,
                         env={**env, **preset}, cwd=ROOT)
    assert out.stdout.split() == [expected, "False"]  # set before torch is imported, so OpenMP reads it


def test_glibc_settings_and_the_master_switch_are_respected():
    assert keep_freed_memory({"MALLOC_MMAP_THRESHOLD_": "131072"}) is False
    assert keep_freed_memory({"GLIBC_TUNABLES": "glibc.malloc.trim_threshold=0"}) is False
    env = {"DEPTHNERF_PROCESS_DEFAULTS": "0"}
    assert configure_process(env) is False and env == {"DEPTHNERF_PROCESS_DEFAULTS": "0"}
