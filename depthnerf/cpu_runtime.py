"""Process-wide CPU runtime settings that the ``depthnerf`` CLI and the benchmarks apply before any work.

Two settings, both measured on the 2-core reference machine (``benchmarks/bench_model.py``, docs/presets.md):

- **OpenMP wait policy** ``PASSIVE`` (unless the environment sets one). With the default (spinning) policy, torch's
  OpenMP threads stall badly whenever another process holds one of the cores: a 64x64 view took 27 s instead of
  1.8 s next to a busy process. PASSIVE threads sleep instead of spinning. It must be set before torch is
  imported, because the OpenMP runtime reads it once.
- **glibc malloc keeps freed memory.** glibc serves every allocation above its mmap threshold (adaptive, at most
  32 MiB by default) with fresh pages from ``mmap`` and returns them on ``free``, so each large activation of a
  training step is page-faulted in anew. One fp32 ``[49152, 512]`` MLP activation of the paper preset is 96 MiB,
  and a ReLU over it took 39 ms with fresh pages against 6 ms on reused ones. The paper-preset training iteration
  took 18.2 s instead of 9.7 s. :func:`keep_freed_memory` raises the mmap and trim thresholds (``mallopt``) so
  freed blocks stay in the heap and are reused. The cost is that the process keeps its peak heap: RSS 6 GB
  instead of 3.6 GB for a paper-preset training step. This is the effect the PyTorch CPU tuning guide gets by
  preloading jemalloc or tcmalloc. It is a no-op on other C libraries and when ``DEPTHNERF_MALLOC_TUNING=0``.

Python API users get the same speed by calling :func:`configure_process` (or just :func:`keep_freed_memory`)
once at start-up; the library itself never changes process-wide settings behind a caller's back.
"""

from __future__ import annotations

import ctypes
import os
import platform
from collections.abc import MutableMapping

OMP_WAIT_POLICY = "PASSIVE"
"""OpenMP wait policy set unless the environment already sets ``OMP_WAIT_POLICY``."""

MMAP_THRESHOLD = 1 << 30
"""Allocations below this many bytes (1 GiB) come from the heap instead of a fresh ``mmap``."""

TRIM_THRESHOLD = 2**31 - 1
"""Free memory at the top of the heap is returned to the OS only above this many bytes (``mallopt`` takes an int)."""

OPT_OUT_VARIABLE = "DEPTHNERF_MALLOC_TUNING"
"""Environment variable; ``0`` leaves glibc's malloc at its defaults (lower RSS, slower large-batch training)."""

_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc <malloc.h> parameter numbers


def set_omp_wait_policy(environ: MutableMapping[str, str] | None = None) -> None:
    """Set ``OMP_WAIT_POLICY=PASSIVE`` unless already set; effective only before torch is imported."""
    (os.environ if environ is None else environ).setdefault("OMP_WAIT_POLICY", OMP_WAIT_POLICY)


def keep_freed_memory(environ: MutableMapping[str, str] | None = None) -> bool:
    """Raise glibc's mmap and trim thresholds so freed tensors are reused instead of unmapped.

    Returns True when both settings were applied. Returns False on a non-glibc C library or when
    ``DEPTHNERF_MALLOC_TUNING=0``. Affects only allocations made after the call.
    """
    env = os.environ if environ is None else environ
    if env.get(OPT_OUT_VARIABLE, "1") == "0" or platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return False
    return bool(libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(libc.mallopt(_M_TRIM_THRESHOLD,
                                                                                        TRIM_THRESHOLD))


def configure_process(environ: MutableMapping[str, str] | None = None) -> bool:
    """Both settings above. Returns whether the malloc tuning was applied."""
    set_omp_wait_policy(environ)
    return keep_freed_memory(environ)
