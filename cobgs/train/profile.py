"""Where a training step's time goes: per-phase timers for :class:`cobgs.train.optimize.Trainer`.

A :class:`PhaseTimer` given to a trainer (``trainer.timer = PhaseTimer(device)``) times the
phases of every step: ``render`` (the forward pass, SH colours included), ``loss`` (L1 + SSIM),
``backward``, ``stats`` (the densification statistics), ``optimizer`` (Adam and zeroing the
gradients), ``densify`` (clone / split / prune / opacity reset, on the steps that do them) and
``sync`` (the step's host synchronisation: the loss and PSNR read back). On a CUDA device
each phase is a pair of CUDA events, read once at the end (:meth:`PhaseTimer.report`), so
timing adds no synchronisation of its own; on the CPU, wall-clock time. Without a timer the
trainer's phases cost nothing extra.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from typing import Iterator

PHASES = ("render", "loss", "backward", "stats", "optimizer", "densify", "sync")


class PhaseTimer:
    """Per-phase times of the steps it watches (module docstring)."""

    def __init__(self, device="cpu"):
        import torch

        self.device = torch.device(device)
        self.cuda = self.device.type == "cuda"
        self._events: dict[str, list] = {p: [] for p in PHASES}
        self._seconds: dict[str, float] = {p: 0.0 for p in PHASES}
        self._counts: dict[str, int] = {p: 0 for p in PHASES}
        self.steps = 0

    @contextmanager
    def phase(self, name: str) -> Iterator[None]:
        """Time the block as phase ``name`` (one of :data:`PHASES`)."""
        if self.cuda:
            import torch

            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
            try:
                yield
            finally:
                end.record()
                self._events[name].append((start, end))
        else:
            t0 = time.perf_counter()
            try:
                yield
            finally:
                self._seconds[name] += time.perf_counter() - t0
        self._counts[name] += 1

    def report(self) -> dict:
        """``{"steps", "device", "phases": {phase: {"ms_per_step", "share", "calls"}}, "ms_per_step"}``
        (one synchronisation on CUDA, here)."""
        if self.cuda:
            import torch

            torch.cuda.synchronize(self.device)
            for name, pairs in self._events.items():
                self._seconds[name] += sum(s.elapsed_time(e) for s, e in pairs) / 1000.0
                pairs.clear()
        total = sum(self._seconds.values())
        steps = max(self.steps, 1)
        phases = {p: {"ms_per_step": 1000.0 * s / steps, "share": s / total if total else 0.0,
                      "calls": self._counts[p]} for p, s in self._seconds.items()}
        return {"steps": self.steps, "device": str(self.device), "phases": phases,
                "ms_per_step": 1000.0 * total / steps}


@contextmanager
def no_phase(name: str) -> Iterator[None]:
    """The trainer's phase when no timer watches it: nothing."""
    yield


__all__ = ["PHASES", "PhaseTimer", "no_phase"]
