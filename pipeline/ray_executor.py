"""The Ray executor: each task is a Ray task with the stage's declared CPU / GPU needs.

The driver keeps scheduling (what is cached, what is ready, what failed) exactly as for
the local executors and only hands ready tasks to Ray, so progress lines and failure
records are the same. Workers read and write the cache folder directly: on a cluster it
must be on a filesystem every node mounts at the same path, and every node needs the same
``cobgs`` (and stage code) installed. Ray is optional: ``pip install 'cobgs[ray]'``.

Peak memory of a Ray task is measured in the Ray worker process the same way as locally
(VmHWM reset at task start), so it is that task's own peak even on a reused worker.
"""

from __future__ import annotations

import sys
import time
from typing import Any, Optional

from .errors import ExecutorError
from .execute import Job, JobResult, execute, record_crash
from .stage import Resources

INSTALL_HINT = ("the Ray executor needs Ray, an optional extra: pip install 'cobgs[ray]' "
                "(or pip install 'ray[default]')")


def _ray_execute(job: Job) -> JobResult:
    import os

    try:  # the manifest records which Ray node ran the task (see execute's manifest)
        import ray

        os.environ["COBGS_RAY_NODE"] = ray.get_runtime_context().get_node_id()
    except Exception:  # noqa: BLE001 - only a record; never fail the task for it
        pass
    result = execute(job)
    if result.status == "interrupted":
        # ray.cancel raised KeyboardInterrupt in the task and execute() cleaned up; Ray
        # expects the interruption to propagate (a task that returns instead is never
        # marked finished).
        raise KeyboardInterrupt
    return result


def import_ray() -> Any:
    try:
        import ray
    except ImportError:
        raise ExecutorError(INSTALL_HINT) from None
    return ray


#: How long reaching a cluster may take (``$COBGS_RAY_CONNECT_TIMEOUT`` seconds): Ray's own
#: client retries an unreachable address for many minutes, deaf to SIGTERM.
CONNECT_TIMEOUT_S = 60.0
#: The TCP probe of ``host:port`` before Ray is asked to connect.
PROBE_TIMEOUT_S = 10.0


def _host_port(address: str) -> Optional[tuple[str, int]]:
    """(host, port) of ``host:port`` / ``ray://host:port``; None for ``auto`` and the like."""
    text = address[len("ray://"):] if address.startswith("ray://") else address
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or not host:
        return None
    return host.strip("[]"), int(port)


def probe_address(address: str, timeout: float = PROBE_TIMEOUT_S) -> None:
    """Refuse an address nothing listens on, in seconds rather than Ray's minutes.

    Raises:
        ExecutorError: naming the address and what the connection attempt said.
    """
    import socket

    hp = _host_port(address)
    if hp is None:
        return
    t0 = time.monotonic()
    try:
        with socket.create_connection(hp, timeout=timeout):
            pass
    except OSError as exc:
        why = "timed out" if isinstance(exc, TimeoutError) else (exc.strerror or str(exc))
        took = time.monotonic() - t0
        raise ExecutorError(f"cannot reach the Ray cluster at {address}: {why} (after {took:.1f} s); is the head "
                            "node up (`ray start --head`) and the address its GCS port (6379 by default) or its "
                            "client port (ray://HOST:10001)?") from None


def _connect(ray: Any, address: Optional[str]) -> None:
    """``ray.init`` with a deadline, and Ctrl-C / SIGTERM that end the process while it blocks.

    While Ray connects, the main thread sits in native code where no Python signal handler
    runs (Ray's own SIGTERM handler included), so a watcher thread takes SIGINT / SIGTERM
    with ``sigtimedwait`` (the main thread blocks them meanwhile) and ends the process with
    one line; nothing of the run has started yet. The same wait gives up at the deadline.
    """
    import os
    import signal
    import threading

    timeout = float(os.environ.get("COBGS_RAY_CONNECT_TIMEOUT", CONNECT_TIMEOUT_S))
    where = f"the Ray cluster at {address}" if address else "a local Ray instance"
    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "sigtimedwait"):
        try:
            ray.init(address=address, include_dashboard=False, log_to_driver=True)
        except Exception as exc:  # noqa: BLE001 - Ray raises many types here
            raise ExecutorError(f"cannot start or reach {where}: {exc}") from exc
        return
    done = signal.SIGUSR2  # sent by this function to its own watcher when ray.init returned
    watched = {signal.SIGINT, signal.SIGTERM, done}

    def watch() -> None:
        info = signal.sigtimedwait(watched, timeout)
        if info is not None and info.si_signo == done:
            return
        if info is None:
            print(f"cobgs run: error: cannot start or reach {where} within {timeout:g} s "
                  "(COBGS_RAY_CONNECT_TIMEOUT); nothing was run", file=sys.stderr, flush=True)
            os._exit(2)
        name = signal.Signals(info.si_signo).name
        print(f"cobgs run: {name} while connecting to {where}; nothing was run", file=sys.stderr, flush=True)
        os._exit(128 + info.si_signo)

    old = signal.pthread_sigmask(signal.SIG_BLOCK, watched)  # the watcher inherits the mask
    watcher = threading.Thread(target=watch, name="cobgs-ray-connect", daemon=True)
    watcher.start()
    try:
        ray.init(address=address, include_dashboard=False, log_to_driver=True)
    except Exception as exc:  # noqa: BLE001 - Ray raises many types here
        raise ExecutorError(f"cannot start or reach {where}: {exc}") from exc
    finally:
        signal.pthread_kill(watcher.ident, done)
        watcher.join()
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


#: The reaper of a local Ray instance (a separate, tiny process in its own session): while the
#: driver lives it notes, every :data:`REAP_POLL_S`, the driver's descendants (Ray's GCS, raylet,
#: agents, workers) with their start times; when its stdin closes without "done" (the driver was
#: killed: SIGKILL, SIGTERM, the OOM killer), it sends SIGTERM to those still alive and to what
#: they started, then SIGKILL after :data:`REAP_GRACE_S`. Ray's own agents otherwise outlive a
#: killed driver by a minute or two. Only the driver's own descendants are ever signalled.
REAP_POLL_S = 1.0
REAP_GRACE_S = 2.0
_REAPER = r"""
import os, select, signal, sys, time
for s in (signal.SIGINT, signal.SIGHUP):
    signal.signal(s, signal.SIG_IGN)
driver, poll, grace, me = int(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3]), os.getpid()

def table():
    out = {}
    for name in os.listdir("/proc"):
        if name.isdigit():
            try:
                with open(f"/proc/{name}/stat", "rb") as f:
                    rest = f.read().rsplit(b")", 1)[1].split()
                out[int(name)] = (int(rest[1]), rest[19])
            except (OSError, IndexError, ValueError):
                pass
    return out

def below(roots, t):
    kids = {}
    for pid, (ppid, _) in t.items():
        kids.setdefault(ppid, []).append(pid)
    seen, todo = set(), list(roots)
    while todo:
        for c in kids.get(todo.pop(), []):
            if c not in seen and c != me:
                seen.add(c)
                todo.append(c)
    return seen

known = {}
while True:
    ready, _, _ = select.select([0], [], [], poll)
    if ready:
        data = os.read(0, 64)
        if b"done" in data:
            sys.exit(0)
        if not data:
            break
    t = table()
    for pid in below([driver], t):
        known[pid] = t[pid][1]
t = table()
alive = {pid for pid, start in known.items() if t.get(pid, (0, None))[1] == start}
targets = alive | below(alive, t)
for sig in (signal.SIGTERM, signal.SIGKILL):
    for pid in targets:
        try:
            os.kill(pid, sig)
        except OSError:
            pass
    deadline = time.monotonic() + grace
    while sig == signal.SIGTERM and time.monotonic() < deadline:
        t = table()
        targets = {pid for pid in targets if pid in t}
        if not targets:
            sys.exit(0)
        time.sleep(0.1)
"""


def start_reaper(driver: int) -> Any:
    """The reaper of :data:`_REAPER` for ``driver``'s local Ray instance (Linux: /proc); None
    where it cannot start (then Ray's own clean-up applies)."""
    import os
    import subprocess

    if not os.path.isdir("/proc"):
        return None
    try:
        return subprocess.Popen([sys.executable, "-c", _REAPER, str(driver), str(REAP_POLL_S), str(REAP_GRACE_S)],
                                stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                start_new_session=True, close_fds=True)
    except OSError:
        return None


class RayExecutor:
    """Submits jobs as Ray tasks; starts a local Ray instance unless one is running or an
    ``address`` (``auto``, ``ray://host:10001``, ``host:6379``) is given. An address that
    nothing listens on is refused within :data:`PROBE_TIMEOUT_S`, and connecting may take at
    most :data:`CONNECT_TIMEOUT_S`. The processes of a local instance this driver started end
    within seconds of the driver, however it ends (:data:`_REAPER`)."""

    name = "ray"
    submitted_state = "queued"  # Ray starts it when a node has room

    def __init__(self, address: Optional[str] = None):
        ray = import_ray()
        self._ray = ray
        self._owned = False
        self._reaper = None
        if not ray.is_initialized():
            if address:
                probe_address(address)
            import os

            if not address:  # a local instance: its processes are this driver's descendants
                self._reaper = start_reaper(os.getpid())
            _connect(ray, address)
            self._owned = True
        self._remote = ray.remote(max_retries=0)(_ray_execute)
        self._running: dict[Any, Job] = {}
        self._rejected: list[JobResult] = []
        self._cluster = ray.cluster_resources()
        nodes = [n for n in ray.nodes() if n.get("Alive")]
        # the largest single node: a task cannot span nodes
        self._node_max = {what: max((float(n.get("Resources", {}).get(what, 0.0)) for n in nodes), default=0.0)
                          for what in ("CPU", "GPU")}
        self._fitted: set[str] = set()

    def capacity(self) -> Optional[int]:
        return None

    def submit(self, job: Job, resources: Resources) -> None:
        # A task asking for more than the whole cluster has would wait forever in Ray's
        # queue; fail it now with the reason instead.
        for what, need in (("GPU", resources.gpus), ("CPU", resources.cpus)):
            have = self._cluster.get(what, 0.0)
            if need > have:
                self._rejected.append(JobResult(
                    job.index, "failed", job.key,
                    error=f"needs {need:g} {what}(s) (device={job.settings.device}) but the "
                          f"Ray cluster has {have:g}"))
                return
        # A request larger than every node waits forever in Ray's queue ("No available node
        # types can fulfill resource request"): CPUs are fitted to the largest node (a
        # stage's CPU count sizes its threads, it still runs with fewer); GPUs cannot be.
        if resources.gpus > self._node_max["GPU"]:
            self._rejected.append(JobResult(
                job.index, "failed", job.key,
                error=f"needs {resources.gpus:g} GPU(s) on one node but the largest Ray node has "
                      f"{self._node_max['GPU']:g}"))
            return
        cpus = resources.cpus
        if cpus > self._node_max["CPU"] > 0:
            cpus = self._node_max["CPU"]
            if job.stage.name not in self._fitted:
                self._fitted.add(job.stage.name)
                print(f"note: stage {job.stage.name!r} asks for {resources.cpus:g} CPUs; the largest Ray "
                      f"node has {cpus:g}: its tasks run with {cpus:g}", file=sys.stderr, flush=True)
        options: dict[str, Any] = {"num_cpus": cpus, "num_gpus": resources.gpus,
                                   "name": f"{job.stage.name}[{job.item.label}]"}
        if resources.memory_gb:
            options["memory"] = int(resources.memory_gb * 2**30)
        ref = self._remote.options(**options).remote(job)
        self._running[ref] = job

    def running(self) -> int:
        return len(self._running) + len(self._rejected)

    def _collect(self, ref: Any, record: bool = True, timeout: Optional[float] = None
                 ) -> JobResult:
        ray = self._ray
        job = self._running.pop(ref)
        try:
            return ray.get(ref, timeout=timeout)
        except (ray.exceptions.TaskCancelledError, ray.exceptions.GetTimeoutError):
            return JobResult(job.index, "interrupted", job.key)
        except Exception as exc:  # noqa: BLE001 - worker crash, node loss, unpicklable job
            if not record:
                return JobResult(job.index, "interrupted", job.key)
            reason = f"Ray task failed: {type(exc).__name__}: {str(exc).strip()[:500]}"
            return record_crash(job, reason)

    def wait(self) -> list[JobResult]:
        if self._rejected:
            out, self._rejected = self._rejected, []
            return out
        ray = self._ray
        refs = list(self._running)
        ready, _ = ray.wait(refs, num_returns=1)
        more, _ = ray.wait([r for r in refs if r not in ready], num_returns=len(refs) - 1,
                           timeout=0) if len(refs) > 1 else ([], [])
        return [self._collect(r) for r in list(ready) + list(more)]

    def interrupt(self) -> list[JobResult]:
        ray = self._ray
        for ref in self._running:
            ray.cancel(ref)  # raises KeyboardInterrupt in the task: it cleans up its entry
        results = []
        deadline = time.monotonic() + 30.0
        for ref in list(self._running):
            left = max(0.1, deadline - time.monotonic())
            if left <= 0.1:
                ray.cancel(ref, force=True)  # did not stop in time
            result = self._collect(ref, record=False, timeout=left)
            if result.status not in ("ok", "cached"):
                result.status = "interrupted"
            results.append(result)
        return results

    def close(self) -> None:
        if self._running:
            self.interrupt()
        if self._owned:
            self._ray.shutdown()
        if self._reaper is not None:  # a clean end: the reaper leaves without signalling anyone
            try:
                self._reaper.stdin.write(b"done\n")
                self._reaper.stdin.close()
                self._reaper.wait(timeout=10)
            except (OSError, ValueError, Exception):  # noqa: BLE001 - it is gone already
                pass
            self._reaper = None
