"""Extraction timing: threshold the labels of a random N-Gaussian model and gather the
foreground (and background) models (:func:`cobgs.refine.segment.label_sets` +
:func:`cobgs.refine.segment.subset`), median of ``--reps``; then the same with glibc keeping freed
memory, so fresh output tensors do not page-fault. Target: < 50 ms for 500k Gaussians.

Run (not collected by pytest)::

    .venv/bin/python tests/benchmarks/bm_extract.py [--n 500000] [--reps 21]

(Moved out of the older ``bm_segmentation.py``, whose accuracy rows are now the
``synthetic_bench`` workflow.) Timings use 2 threads with passive OpenMP waiting.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "2")
os.environ.setdefault("OMP_WAIT_POLICY", "passive")

import argparse  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import torch  # noqa: E402

from cobgs.gaussians.model import GaussianModel  # noqa: E402
from cobgs.refine.segment import label_sets, subset  # noqa: E402


def _keep_freed_memory() -> bool:
    """Ask glibc to keep freed memory in the process (no trim, no per-allocation mmap), so
    that fresh output tensors do not page-fault. Process-wide; the benchmark calls it only
    for its second extraction measurement."""
    import ctypes

    try:
        libc = ctypes.CDLL("libc.so.6")
        M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
        return bool(libc.mallopt(M_TRIM_THRESHOLD, 1 << 30)) and bool(libc.mallopt(M_MMAP_THRESHOLD, 1 << 30))
    except OSError:
        return False


def seg_timing(n: int, reps: int) -> str:
    first = _seg_timing(n, reps)
    if not _keep_freed_memory():
        return first + "\n- (glibc mallopt unavailable: no page-fault-free measurement)"
    second = _seg_timing(n, reps)
    return (first + "\n\nThe same with glibc keeping freed memory (``mallopt`` M_TRIM_THRESHOLD / "
            "M_MMAP_THRESHOLD = 1 GiB: output tensors reuse resident pages instead of page-faulting fresh ones):\n"
            + second.split("\n\n", 1)[1])


def _seg_timing(n: int, reps: int) -> str:
    import resource

    g = torch.Generator().manual_seed(0)
    m = GaussianModel(torch.randn(n, 3, generator=g), torch.randn(n, 3, generator=g) - 4,
                      torch.randn(n, 4, generator=g), torch.randn(n, generator=g), torch.randn(n, 1, 3, generator=g),
                      torch.randn(n, 15, 3, generator=g))
    m.add_extra("mask_logit", 4 * torch.randn(n, generator=g), fill=0.0)
    times, times_fg_only, cpu, cpu1 = [], [], [], []
    load0 = os.getloadavg()[0]
    faults0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(reps):
        t0, c0 = time.perf_counter(), time.process_time()
        fg, bg = label_sets(m.data["mask_logit"])
        a = subset(m, fg)
        b = subset(m, bg)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        del a, b
        t0, c0 = time.perf_counter(), time.process_time()
        fg, _ = label_sets(m.data["mask_logit"])
        a = subset(m, fg)
        times_fg_only.append(time.perf_counter() - t0)
        cpu1.append(time.process_time() - c0)
        del a
    faults = (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults0) / (2 * reps)
    fg, bg = label_sets(m.data["mask_logit"])
    a, b = subset(m, fg), subset(m, bg)
    med, med1 = statistics.median(times), statistics.median(times_fg_only)
    return (f"### Segmentation (threshold + gather), {n} Gaussians (SH degree 3, 1 label extra), "
            f"{torch.get_num_threads()} threads, median of {reps}, 1-min load average "
            f"{load0:.1f} → {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs\n\n"
            f"- foreground + background models: {1000 * med:.1f} ms wall, "
            f"{1000 * statistics.median(cpu):.1f} ms process CPU "
            f"({len(a)} fg / {len(b)} bg Gaussians)\n- foreground model only: {1000 * med1:.1f} ms wall, "
            f"{1000 * statistics.median(cpu1):.1f} ms process CPU\n"
            f"- minor page faults per extraction (mean): {faults:.0f}\n"
            f"- target < 50 ms: object extraction {'met' if med1 < 0.05 else 'NOT met'}; "
            f"object + removal scene {'met' if med < 0.05 else 'NOT met'}")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=500_000, help="Gaussians in the random model")
    ap.add_argument("--reps", type=int, default=21)
    args = ap.parse_args(argv)
    torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))
    print(seg_timing(args.n, args.reps), flush=True)


if __name__ == "__main__":
    main()
