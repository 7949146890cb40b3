"""Wall time, CPU time and peak memory of one task, measured in the process that runs it.

Peak memory is the resident-set high-water mark (``VmHWM``) of that process. Before the
task starts the mark is reset by writing ``5`` to ``/proc/self/clear_refs`` (Linux >= 4.0),
so a long-lived worker (the driver with ``--jobs 1``, a Ray worker) reports the peak of
this task rather than of its whole life; the baseline it already had resident is included
(after returning freed heap memory to the OS, ``malloc_trim``, so that memory an earlier
task freed but the allocator kept is not counted).
Where the reset is refused the lifetime ``ru_maxrss`` is reported and the manifest says so
(``peak_rss_scope = "process"``). Subprocesses the stage starts are reported apart, as the
largest peak among the children it waited for (``children_peak_rss_bytes``).

GPU memory: when the task's process has PyTorch loaded with CUDA initialised, the peak
memory allocated by PyTorch's caching allocator on the current device during the task is
recorded as ``gpu_peak_bytes`` (the counters are reset at the start when CUDA is already
initialised; a task that initialises CUDA itself starts from zero anyway). The engine never
imports torch: a task that did not use it records ``null``.
"""

from __future__ import annotations

import resource
import sys
import time
from typing import Any, Optional


def _vm_hwm_bytes() -> Optional[int]:
    try:
        with open("/proc/self/status", "rb") as f:
            for line in f:
                if line.startswith(b"VmHWM:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def _trim_heap() -> None:
    """Hand memory the C allocator keeps after frees back to the OS (glibc ``malloc_trim``).

    A process may keep freed memory resident on purpose (cobgs raises glibc's trim
    threshold during training); without this, what an earlier task freed would still be
    resident and counted in the next task's peak. A no-op elsewhere."""
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def _reset_hwm() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _torch_cuda():
    """``torch.cuda`` when the process has already imported torch and initialised CUDA."""
    torch = sys.modules.get("torch")
    cuda = getattr(torch, "cuda", None)
    try:
        if cuda is not None and cuda.is_initialized():
            return cuda
    except Exception:  # noqa: BLE001 - a broken CUDA runtime must not fail the task record
        pass
    return None


def _reset_gpu_peak() -> None:
    cuda = _torch_cuda()
    if cuda is not None:
        try:
            cuda.reset_peak_memory_stats()
        except Exception:  # noqa: BLE001
            pass


def _gpu_peak_bytes() -> Optional[int]:
    cuda = _torch_cuda()
    if cuda is None:
        return None
    try:
        return int(cuda.max_memory_allocated())
    except Exception:  # noqa: BLE001
        return None


class Meter:
    """Start on construction; :meth:`stop` returns the manifest's measurement fields."""

    def __init__(self) -> None:
        _trim_heap()
        self._scope = "task" if _reset_hwm() and _vm_hwm_bytes() is not None else "process"
        self._self0 = resource.getrusage(resource.RUSAGE_SELF)
        self._child0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        _reset_gpu_peak()
        self._t0 = time.perf_counter()
        self.started = time.time()

    def stop(self) -> dict[str, Any]:
        wall = time.perf_counter() - self._t0
        ru = resource.getrusage(resource.RUSAGE_SELF)
        ch = resource.getrusage(resource.RUSAGE_CHILDREN)
        peak = _vm_hwm_bytes() if self._scope == "task" else ru.ru_maxrss * 1024
        child_peak = ch.ru_maxrss * 1024 if ch.ru_maxrss > self._child0.ru_maxrss else None
        return {
            "started": self.started,
            "finished": time.time(),
            "wall_s": round(wall, 6),
            "cpu_s": round((ru.ru_utime - self._self0.ru_utime)
                           + (ru.ru_stime - self._self0.ru_stime), 6),
            "cpu_children_s": round((ch.ru_utime - self._child0.ru_utime)
                                    + (ch.ru_stime - self._child0.ru_stime), 6),
            "peak_rss_bytes": peak,
            "peak_rss_scope": self._scope,
            "children_peak_rss_bytes": child_peak,
            "gpu_peak_bytes": _gpu_peak_bytes(),
        }
