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

``import depthnerf`` applies both (``depthnerf/__init__.py`` calls :func:`configure_process` before anything
imports torch), so the Python API runs as fast as the CLI. Neither overrides an explicit choice: an
``OMP_WAIT_POLICY`` already in the environment is kept, and the malloc thresholds are left alone when glibc's own
``MALLOC_MMAP_THRESHOLD_`` / ``MALLOC_TRIM_THRESHOLD_`` or a ``glibc.malloc`` tunable is set.
``DEPTHNERF_PROCESS_DEFAULTS=0`` turns both off (the process keeps its settings); ``DEPTHNERF_MALLOC_TUNING=0``
only the malloc one. Importing torch before depthnerf leaves the wait policy without effect in that process
(OpenMP reads it when torch loads it): set ``OMP_WAIT_POLICY=PASSIVE`` in the environment then.
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

OPT_OUT_ALL_VARIABLE = "DEPTHNERF_PROCESS_DEFAULTS"
"""Environment variable; ``0`` makes :func:`configure_process` (``import depthnerf``, the CLI) change nothing."""

GLIBC_MALLOC_VARIABLES = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")
"""glibc's own malloc settings; when one is set (or ``GLIBC_TUNABLES`` names a ``glibc.malloc`` tunable), the
user chose the allocator's behaviour and :func:`keep_freed_memory` leaves it alone."""

_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc <malloc.h> parameter numbers


def set_omp_wait_policy(environ: MutableMapping[str, str] | None = None) -> None:
    """Set ``OMP_WAIT_POLICY=PASSIVE`` unless already set; effective only before torch is imported."""
    (os.environ if environ is None else environ).setdefault("OMP_WAIT_POLICY", OMP_WAIT_POLICY)


def keep_freed_memory(environ: MutableMapping[str, str] | None = None) -> bool:
    """Raise glibc's mmap and trim thresholds so freed tensors are reused instead of unmapped.

    Returns True when both settings were applied. Returns False on a non-glibc C library, when
    ``DEPTHNERF_MALLOC_TUNING=0`` or when the environment sets glibc's malloc itself
    (:data:`GLIBC_MALLOC_VARIABLES`). Affects only allocations made after the call.
    """
    env = os.environ if environ is None else environ
    if env.get(OPT_OUT_VARIABLE, "1") == "0" or platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    if any(name in env for name in GLIBC_MALLOC_VARIABLES) or "glibc.malloc." in env.get("GLIBC_TUNABLES", ""):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return False
    return bool(libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(libc.mallopt(_M_TRIM_THRESHOLD,
                                                                                        TRIM_THRESHOLD))


def configure_process(environ: MutableMapping[str, str] | None = None) -> bool:
    """Both settings above, unless ``DEPTHNERF_PROCESS_DEFAULTS=0``. Returns whether the malloc tuning was
    applied."""
    if (os.environ if environ is None else environ).get(OPT_OUT_ALL_VARIABLE, "1") == "0":
        return False
    set_omp_wait_policy(environ)
    return keep_freed_memory(environ)
