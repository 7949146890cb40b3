"""cobgs.memory: the glibc thresholds that keep per-iteration tensors from page-faulting."""

import subprocess
import sys
import textwrap

import pytest

from cobgs import memory


def _run(code: str, **env) -> str:
    import os

    e = dict(os.environ)
    e.pop("COBGS_RETAIN_FREED_MEMORY", None)
    e.update(env)
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
                         env=e, timeout=120)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip()


# Allocate and free a 64 MiB block 20 times, count minor page faults (fresh process).
_FAULTS = """
    import resource, ctypes
    from cobgs.memory import retain_freed_memory
    print(retain_freed_memory(), end=" ")
    libc = ctypes.CDLL("libc.so.6")
    libc.malloc.restype = ctypes.c_void_p
    libc.free.argtypes = (ctypes.c_void_p,)
    n = 64 << 20
    def touch():
        p = libc.malloc(n)
        ctypes.memset(p, 1, n)
        libc.free(p)
    touch()
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(20):
        touch()
    print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc mallopt")
def test_freed_blocks_are_reused_instead_of_faulted_in_again():
    on, faults_on = _run(_FAULTS).split()
    off, faults_off = _run(_FAULTS, COBGS_RETAIN_FREED_MEMORY="0").split()
    assert (on, off) == ("True", "False")
    pages = 20 * (64 << 20) // 4096
    assert int(faults_off) > 0.5 * pages  # every round maps and faults the block afresh
    assert int(faults_on) < 0.05 * pages  # the heap keeps it


def test_idempotent_and_reported(monkeypatch):
    first = memory.retain_freed_memory()
    assert memory.retain_freed_memory() is first


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc mallopt, /proc")
def test_task_peak_excludes_memory_an_earlier_task_freed_but_the_allocator_kept():
    # The pipeline meters each task's peak RSS from a reset high-water mark; with freed
    # memory retained, the meter must first hand it back (malloc_trim) or the next task's
    # peak would include it.
    out = _run("""
        import ctypes
        from cobgs.memory import retain_freed_memory
        from pipeline.measure import Meter
        assert retain_freed_memory()
        libc = ctypes.CDLL("libc.so.6")
        libc.malloc.restype = ctypes.c_void_p
        libc.free.argtypes = (ctypes.c_void_p,)
        m = Meter()
        p = libc.malloc(256 << 20)
        ctypes.memset(p, 1, 256 << 20)
        libc.free(p)
        big = m.stop()["peak_rss_bytes"]
        small = Meter().stop()["peak_rss_bytes"]
        print(big >> 20, small >> 20)
    """)
    big, small = map(int, out.split())
    assert big - small > 200, (big, small)
