"""Keep freed memory in the process instead of returning it to the OS (glibc only).

A training or refinement iteration allocates and frees the same large tensors every time
(gradients of the SH coefficients, the rasterizer's per-Gaussian records, image-sized
buffers). glibc serves blocks above its mmap threshold (at most 32 MiB with the default
dynamic threshold) with fresh ``mmap`` s and unmaps them on free, so each iteration
page-faults and zero-fills them again. On the trained fern 1/8 scene (249k Gaussians, 2
threads) that was about 16k minor faults and 33 ms of system CPU time per iteration; with
the thresholds raised, 2k faults, 5 ms, and 10 % less wall time per iteration
(``tests/benchmarks/bm_train_iter.py`` prints both), for a peak resident size about 8 %
higher (819 → 887 MiB).

:func:`retain_freed_memory` raises both thresholds with ``mallopt``. It changes the
allocator of the whole process, so the library calls it only where it runs a long
optimisation loop (:class:`cobgs.train.optimize.Trainer`, :class:`cobgs.refine.alternation.Refiner`) and the
``cobgs`` command calls it at start-up. ``COBGS_RETAIN_FREED_MEMORY=0`` turns it off.
Stdlib only (the CLI imports this before torch).
"""

from __future__ import annotations

import ctypes
import os
import sys
import threading

# mallopt parameters (malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
#: Blocks below this come from the heap (reused after free) rather than fresh mmaps.
MMAP_THRESHOLD = 1 << 30
#: Free memory at the top of the heap is returned to the OS only above this much.
TRIM_THRESHOLD = 1 << 30

_lock = threading.Lock()
_state: dict = {}


def retain_freed_memory() -> bool:
    """Raise glibc's mmap and trim thresholds once per process (see the module docstring).

    Returns:
        True when the thresholds are (now or already) raised; False on other C libraries,
        when ``COBGS_RETAIN_FREED_MEMORY=0``, or when ``mallopt`` refused.
    """
    with _lock:
        if "done" in _state:
            return _state["done"]
        _state["done"] = ok = _apply()
        return ok


def release_free_memory() -> None:
    """Return the allocator's free pages to the OS (glibc ``malloc_trim``; no-op elsewhere).

    Memory meters call it before they read a baseline: freed tensors stay in the process
    (glibc raises its mmap threshold after large frees, and :func:`retain_freed_memory`
    keeps them on purpose), so without it the resident size at the start of a method
    already covers what it will allocate and the measured increase reads 0.
    """
    libc = _glibc()
    if libc is not None:
        libc.malloc_trim(0)


def _glibc():
    """glibc with ``mallopt`` and ``malloc_trim``, or None (other platforms / C libraries)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt, libc.malloc_trim  # noqa: B018 - both must exist (not on musl)
    except (OSError, AttributeError):
        return None
    return libc


def _apply() -> bool:
    if os.environ.get("COBGS_RETAIN_FREED_MEMORY", "1").strip() in ("0", "false", "no", "off"):
        return False
    libc = _glibc()
    if libc is None:
        return False
    mallopt = libc.mallopt
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))
