"""Local executors: in the driver (``--jobs 1``) or in forked worker processes (``--jobs N``).

An executor only runs jobs; the scheduler (run.py) decides what runs when, so dependency
order, caching and failure handling are the same for every executor (Ray included, see
ray_executor.py).

``--jobs N`` forks one process per task (at most N at a time). Forking per task keeps every
task's memory, CUDA context and crashes to itself: a segfault or an out-of-memory kill
fails that task only, and its peak RSS is its own (plus the driver pages it shares).
"""

from __future__ import annotations

import multiprocessing
import multiprocessing.connection
import os
import signal
import sys
import time
from typing import Any, Optional, Protocol

from .execute import Job, JobResult, execute, record_crash
from .stage import Resources


class Executor(Protocol):
    name: str

    def capacity(self) -> Optional[int]:
        """How many jobs may run at once (None: the executor queues by itself)."""

    def submit(self, job: Job, resources: Resources) -> None: ...

    def wait(self) -> list[JobResult]:
        """Block until at least one submitted job finished; return the finished ones."""

    def running(self) -> int: ...

    def interrupt(self) -> list[JobResult]:
        """Stop every running job (their entries are discarded); return their results."""

    def close(self) -> None: ...


class InlineExecutor:
    """Runs each job in the driver process when the scheduler waits for it."""

    name = "local"

    def __init__(self) -> None:
        self._queue: list[Job] = []

    def capacity(self) -> Optional[int]:
        return 1

    def submit(self, job: Job, resources: Resources) -> None:
        self._queue.append(job)

    def running(self) -> int:
        return len(self._queue)

    def wait(self) -> list[JobResult]:
        job = self._queue.pop(0)
        try:
            return [execute(job)]
        except KeyboardInterrupt:  # arrived outside the stage (lock, bookkeeping)
            return [JobResult(job.index, "interrupted", job.key)]

    def interrupt(self) -> list[JobResult]:
        out = [JobResult(j.index, "interrupted", j.key) for j in self._queue]
        self._queue.clear()
        return out

    def close(self) -> None:
        pass


def _quiet_interrupts(unraisable: Any) -> None:
    """sys.unraisablehook of a worker: a Ctrl-C that lands inside a callback Python cannot
    raise from (a weakref callback of the import machinery, a finaliser) is not printed as
    a stray traceback; the parent's interrupt sequence (see ForkExecutor.interrupt) signals
    the worker again if it keeps running. Everything else is reported as usual."""
    if isinstance(unraisable.exc_value, KeyboardInterrupt):
        return
    sys.__unraisablehook__(unraisable)


def die_with_parent(parent_pid: int) -> None:
    """End this process when its parent dies, whatever kills the parent (SIGKILL, SIGTERM,
    the OOM killer): Linux's PR_SET_PDEATHSIG sends it SIGKILL then. Where that is not
    available nothing changes. A parent that died before the call ends it at once."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGKILL), 0, 0, 0)  # 1 = PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if os.getppid() != parent_pid:
        os._exit(1)


def _child_main(job: Job, conn: Any, parent_pid: int) -> None:
    die_with_parent(parent_pid)
    sys.unraisablehook = _quiet_interrupts
    try:
        # SIGINT was blocked across fork (see ForkExecutor.submit); one that arrived
        # meanwhile is delivered here and becomes an ordinary interruption.
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
        result = execute(job)
    except KeyboardInterrupt:
        result = JobResult(job.index, "interrupted", job.key)
    except BaseException as exc:  # noqa: BLE001 - reported, never lost
        result = JobResult(job.index, "failed", job.key, error=f"worker error: {exc!r}")
    try:
        conn.send(result)
        conn.close()
        sys.stdout.flush()
        sys.stderr.flush()
    finally:
        os._exit(0)  # skip the parent's atexit handlers inherited through fork


class ForkExecutor:
    """At most ``jobs`` forked worker processes, one per task."""

    name = "local-pool"

    def __init__(self, jobs: int):
        self.jobs = jobs
        self._mp = multiprocessing.get_context("fork")
        self._running: dict[Any, tuple[Job, Any]] = {}  # connection -> (job, process)

    def capacity(self) -> Optional[int]:
        return self.jobs

    def submit(self, job: Job, resources: Resources) -> None:
        recv, send = self._mp.Pipe(duplex=False)
        proc = self._mp.Process(target=_child_main, args=(job, send, os.getpid()), daemon=False,
                                name=f"cobgs-{job.stage.name}")
        # A Ctrl-C landing inside fork() would interrupt the child's at-fork handlers
        # (logging's lock re-initialisation) and print a stray traceback; hold it until
        # the child is running and registered here.
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            proc.start()
            send.close()
            self._running[recv] = (job, proc)
        finally:
            signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})

    def running(self) -> int:
        return len(self._running)

    def _collect(self, conn: Any, record: bool = True) -> JobResult:
        job, proc = self._running.pop(conn)
        try:
            result = conn.recv()
        except (EOFError, OSError):
            result = None
        conn.close()
        proc.join()
        if result is None and not record:
            return JobResult(job.index, "interrupted", job.key)
        if result is None:
            code = proc.exitcode
            why = f"killed by signal {-code}" if code is not None and code < 0 else \
                f"exit code {code}"
            result = record_crash(job, f"worker process died without a result ({why})")
        return result

    def wait(self) -> list[JobResult]:
        ready = multiprocessing.connection.wait(list(self._running))
        return [self._collect(conn) for conn in ready]

    def interrupt(self) -> list[JobResult]:
        results: list[JobResult] = []
        # Ctrl-C on a terminal reaches the workers too; give them a moment to clean up
        # on their own before signalling the ones still running.
        for grace, sig in ((2.0, None), (20.0, signal.SIGINT), (5.0, signal.SIGKILL)):
            if not self._running:
                break
            if sig is not None:
                for _, proc in self._running.values():
                    if proc.is_alive():
                        try:
                            os.kill(proc.pid, sig)
                        except ProcessLookupError:
                            pass
            deadline = time.monotonic() + grace
            while self._running and time.monotonic() < deadline:
                for conn in multiprocessing.connection.wait(
                        list(self._running), timeout=max(0.0, deadline - time.monotonic())):
                    result = self._collect(conn, record=False)
                    if result.status not in ("ok", "cached"):
                        result.status = "interrupted"
                    results.append(result)
        return results

    def close(self) -> None:
        self.interrupt()
