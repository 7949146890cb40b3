"""Helpers shared by the benchmark scripts (imported with the scripts' folder on sys.path)."""

from __future__ import annotations

import time


class Clock:
    """Wall time and process CPU time (all threads, user + system) of a block."""

    def __enter__(self) -> "Clock":
        self.wall0, self.cpu0 = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc) -> None:
        self.wall = time.perf_counter() - self.wall0
        self.cpu = time.process_time() - self.cpu0
