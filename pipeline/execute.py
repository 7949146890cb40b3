"""Running one task in whatever process an executor chose, and committing its entry.

The same :func:`execute` runs in the driver (``--jobs 1``), in a forked worker
(``--jobs N``) and in a Ray worker. It takes the entry's lock, re-checks the cache (another
run may have finished the entry meanwhile), runs the stage into a temporary folder,
validates and hashes the outputs, writes the manifest last and renames the folder into
place. Any exception becomes a failure record with the log kept; Ctrl-C discards the
temporary folder and reports ``interrupted``.
"""

from __future__ import annotations

import logging
import os
import platform
import shutil
import signal
import socket
import sys
import threading
import time
import traceback
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Mapping, Optional

from .cache import LOG, MANIFEST, OUT, SCRATCH, Cache, write_json_atomic
from .context import StageContext
from .errors import OutputError
from .hashing import tree_hash
from .items import Item
from .measure import Meter
from .stage import Stage
from .values import Settings

MANIFEST_FORMAT = 1


@dataclass(frozen=True)
class Job:
    """Everything a worker needs to run one task (picklable)."""

    index: int
    stage: Stage
    item: Item
    items: list[Item]
    params: Any
    params_json: Mapping[str, Any]
    key: str
    key_doc: Mapping[str, Any]
    inputs: Mapping[str, Any]  # artifact -> Path, or {Item: Path} for a fan-in
    input_records: Mapping[str, Any]  # artifact -> provenance for the manifest
    settings: Settings
    cache_root: str
    force: bool
    package_version: str
    executor: str
    workflow: str


@dataclass
class JobResult:
    """What a worker reports back. ``status``: ok | cached | failed | interrupted."""

    index: int
    status: str
    key: str
    outputs: Optional[dict] = None
    entry_dir: Optional[str] = None
    wall_s: float = 0.0
    error: str = ""
    log_path: Optional[str] = None
    note: str = ""
    measures: dict = field(default_factory=dict)
    disk_full: bool = False  # the failure was "no space left" on a disk (the cache's, or an output's)


def is_disk_full(exc: BaseException) -> bool:
    """Whether ``exc`` (or an exception it was raised from) is "no space left on device" or
    "disk quota exceeded"."""
    import errno

    seen = set()
    e: Optional[BaseException] = exc
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        if isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT):
            return True
        e = e.__cause__ or e.__context__
    return False


def _close_log(log: logging.Logger, handler: logging.Handler) -> None:
    """Close a task's log handler; on a full disk its last flush fails, which must not
    turn a task's failure into a crash of the failure handler itself."""
    try:
        handler.close()
    except OSError:
        pass
    log.removeHandler(handler)


class _Tee:
    """A text stream writing to the terminal stream and the entry's log file."""

    def __init__(self, primary: Any, log_file: Any):
        self._primary, self._log = primary, log_file

    def write(self, text: str) -> int:
        self._log.write(text)
        return self._primary.write(text)

    def flush(self) -> None:
        self._log.flush()
        self._primary.flush()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._primary, name)


@contextmanager
def _sigint_shielded() -> Iterator[None]:
    """Ignore a second Ctrl-C while cleaning up (main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


def _validate_outputs(stage: Stage, result: Any, out_dir: Path) -> dict[str, Path]:
    where = f"stage {stage.name!r}"
    if not isinstance(result, Mapping):
        raise OutputError(f"{where}: run() must return {{output name: path}} for "
                          f"{list(stage.outputs)}, got {type(result).__name__}")
    missing = [n for n in stage.outputs if n not in result]
    extra = [n for n in result if n not in stage.outputs]
    if missing or extra:
        raise OutputError(f"{where}: run() returned outputs {sorted(result)}, declared "
                          f"{list(stage.outputs)} (missing {missing}, undeclared {extra})")
    root = out_dir.resolve()
    paths = {}
    for name in stage.outputs:
        value = result[name]
        if not isinstance(value, (str, os.PathLike)):
            raise OutputError(f"{where}: output {name!r} must be a path, got {value!r}")
        path = Path(value)
        path = path if path.is_absolute() else out_dir / path
        if not (path.exists() or path.is_symlink()):
            raise OutputError(f"{where}: output {name!r} was returned as {path} but does "
                              "not exist")
        try:
            path.resolve().relative_to(root) if not path.is_symlink() else \
                path.parent.resolve().relative_to(root)
        except ValueError:
            raise OutputError(f"{where}: output {name!r} ({path}) is outside ctx.out_dir "
                              f"({out_dir}); write outputs there") from None
        paths[name] = path
    return paths


def _logger(key: str, log_path: Path) -> tuple[logging.Logger, logging.Handler]:
    # A stand-alone logger (not registered with logging's manager): one per task would
    # otherwise accumulate for the life of the process.
    log = logging.Logger(f"pipeline.task.{key[:16]}", logging.DEBUG)
    log.propagate = False
    handler = logging.FileHandler(log_path, encoding="utf-8")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
    log.addHandler(handler)
    return log, handler


_DIST_OF_MODULE: Optional[Mapping[str, list[str]]] = None
_DIST_VERSION: dict[str, str] = {}


def loaded_distributions() -> dict[str, str]:
    """Versions of the installed distributions whose top-level modules this process has
    imported (so a stage's manifest names the torch / numpy / ... it actually ran with;
    the standard library is not a distribution and is left out)."""
    global _DIST_OF_MODULE
    from importlib import metadata

    if _DIST_OF_MODULE is None:
        try:
            _DIST_OF_MODULE = metadata.packages_distributions()
        except Exception:  # noqa: BLE001 - a broken site-packages entry must not fail a run
            _DIST_OF_MODULE = {}
    out: dict[str, str] = {}
    tops = {name.partition(".")[0] for name in list(sys.modules)}
    for top in tops:
        for dist in _DIST_OF_MODULE.get(top, ()):
            if dist not in _DIST_VERSION:
                try:
                    _DIST_VERSION[dist] = metadata.version(dist)
                except Exception:  # noqa: BLE001
                    _DIST_VERSION[dist] = "unknown"
            out[dist] = _DIST_VERSION[dist]
    return dict(sorted(out.items(), key=lambda kv: kv[0].lower()))


def _base_manifest(job: Job, measures: dict) -> dict[str, Any]:
    return {
        "format": MANIFEST_FORMAT,
        "key": job.key,
        "stage": job.stage.name,
        "version": job.stage.version,
        "params": job.params_json,
        "item": {"id": job.item.id, "values": job.item.to_json(),
                 "attrs": job.key_doc.get("attrs", {})},
        "inputs": job.input_records,
        "device": job.settings.device,
        "uses_device": job.stage.uses_device,
        "host": socket.gethostname(),
        "node": os.environ.get("COBGS_RAY_NODE"),  # the Ray node id under the Ray executor
        "pid": os.getpid(),
        "python": platform.python_version(),
        "package_version": job.package_version,
        "dependencies": loaded_distributions(),
        "executor": job.executor,
        "workflow": job.workflow,
        "log": LOG,
        **measures,
    }


def execute(job: Job) -> JobResult:
    """Run ``job`` under its entry lock and commit the entry; never raises for stage
    errors (they come back as ``failed``)."""
    cache = Cache(job.cache_root)
    stage = job.stage
    lock = cache.lock(stage.name, job.key)
    try:
        lock.acquire(on_wait=lambda holder: print(
            f"  {stage.name}[{job.item.label}]: waiting for another run ({holder})",
            file=sys.stderr, flush=True))
    except KeyboardInterrupt:
        return JobResult(job.index, "interrupted", job.key)
    try:
        check = cache.check(stage.name, job.key)
        if check.state == "done" and not job.force:
            return JobResult(job.index, "cached", job.key, check.manifest["outputs"],
                             os.fspath(cache.entry_dir(stage.name, job.key)),
                             note="finished by another run")
        return _run_locked(job, cache)
    finally:
        lock.release()


def _run_locked(job: Job, cache: Cache) -> JobResult:
    stage = job.stage
    cache.clean_tmp(stage.name, job.key)
    tmp = cache.new_tmp(stage.name, job.key)
    out_dir, scratch = tmp / OUT, tmp / SCRATCH
    out_dir.mkdir()
    log, handler = _logger(job.key, tmp / LOG)
    log.info("stage %s version %s item %s key %s", stage.name, stage.version,
             job.item.label, job.key)
    log.info("params %s", job.params_json)
    ctx = StageContext(stage=stage.name, item=job.item, items=job.items, params=job.params,
                       settings=job.settings, out_dir=out_dir, scratch_path=scratch, log=log,
                       key=job.key)
    meter = Meter()
    old_stdout = sys.stdout
    error: Optional[BaseException] = None
    measures: Optional[dict] = None
    try:
        sys.stdout = _Tee(old_stdout, handler.stream)
        try:
            result = stage.run(ctx, job.inputs)
        finally:
            sys.stdout = old_stdout
            measures = meter.stop()  # the stage's own time; hashing is timed apart
        t_hash = time.perf_counter()
        paths = _validate_outputs(stage, result, out_dir)
        if scratch.exists():
            shutil.rmtree(scratch, ignore_errors=True)
        outputs = {}
        for name, path in paths.items():
            h = tree_hash(path)
            outputs[name] = {"path": path.relative_to(tmp).as_posix(), "sha256": h.sha256,
                             "kind": h.kind, "bytes": h.bytes, "files": h.files}
            if h.sizes is not None:
                outputs[name]["sizes"] = h.sizes
            if h.small:
                outputs[name]["small"] = h.small
        measures["hash_s"] = round(time.perf_counter() - t_hash, 6)
    except BaseException as exc:  # noqa: BLE001 - every failure is recorded, Ctrl-C included
        error = exc
    if measures is None:  # interrupted inside meter.stop() itself
        measures = meter.stop()
    if error is not None:
        with _sigint_shielded():
            return _fail(job, cache, tmp, log, handler, error, measures)
    manifest = _base_manifest(job, measures)
    manifest.update(status="ok", outputs=outputs, extra=ctx.extra)
    log.info("done in %.3f s", measures["wall_s"])
    _close_log(log, handler)
    with _sigint_shielded():
        try:
            write_json_atomic(tmp / MANIFEST, manifest)  # last file written
            final = cache.commit(tmp, stage.name, job.key)
            cache.clear_failure(stage.name, job.key)
        except OSError as exc:
            shutil.rmtree(tmp, ignore_errors=True)
            return JobResult(job.index, "failed", job.key, wall_s=measures["wall_s"],
                             error=f"cannot commit the entry: {exc}", disk_full=is_disk_full(exc))
    return JobResult(job.index, "ok", job.key, outputs, os.fspath(final),
                     wall_s=measures["wall_s"], measures=measures, note=warnings_note(ctx.extra))


def warnings_note(extra: Any) -> str:
    """The progress-line note of a task's warnings (``ctx.warn``), "" without any."""
    w = (extra or {}).get("warnings") if isinstance(extra, dict) else None
    return ("WARNING: " + " | ".join(str(x) for x in w)) if isinstance(w, list) and w else ""


def _fail(job: Job, cache: Cache, tmp: Path, log: logging.Logger, handler: logging.Handler,
          exc: BaseException, measures: dict) -> JobResult:
    wall = measures["wall_s"]
    if isinstance(exc, KeyboardInterrupt):
        log.warning("interrupted after %.3f s; the entry is discarded", wall)
        _close_log(log, handler)
        shutil.rmtree(tmp, ignore_errors=True)
        return JobResult(job.index, "interrupted", job.key, wall_s=wall)
    summary = f"{type(exc).__name__}: {exc}".strip()
    full = is_disk_full(exc)
    log.error("failed after %.3f s\n%s", wall,
              "".join(traceback.format_exception(type(exc), exc, exc.__traceback__)))
    _close_log(log, handler)
    manifest = _base_manifest(job, measures)
    manifest.update(status="failed", outputs={}, error={
        "type": type(exc).__name__, "summary": summary,
        "traceback": "".join(traceback.format_exception(type(exc), exc, exc.__traceback__)),
    })
    try:
        folder = cache.record_failure(tmp, job.stage.name, job.key, manifest)
        log_path: Optional[str] = os.fspath(folder / LOG)
    except OSError as exc2:
        shutil.rmtree(tmp, ignore_errors=True)
        log_path = None
        full = full or is_disk_full(exc2)
    return JobResult(job.index, "failed", job.key, wall_s=wall, error=summary,
                     log_path=log_path, measures=measures, disk_full=full)


def record_crash(job: Job, reason: str) -> JobResult:
    """Driver-side failure record for a worker that died without reporting (SIGKILL,
    out of memory): keeps whatever log its temporary folder holds."""
    cache = Cache(job.cache_root)
    leftovers = cache.tmp_leftovers(job.stage.name, job.key)
    manifest = _base_manifest(job, {})
    manifest.update(status="failed", outputs={},
                    error={"type": "WorkerDied", "summary": reason, "traceback": ""})
    lock = cache.lock(job.stage.name, job.key)
    if not lock.acquire(blocking=False):  # someone else is (re)computing it now
        return JobResult(job.index, "failed", job.key, error=reason)
    try:
        tmp = leftovers[-1] if leftovers else cache.new_tmp(job.stage.name, job.key)
        folder = cache.record_failure(tmp, job.stage.name, job.key, manifest)
        cache.clean_tmp(job.stage.name, job.key)
    finally:
        lock.release()
    return JobResult(job.index, "failed", job.key, error=reason,
                     log_path=os.fspath(folder / LOG) if (folder / LOG).exists() else None)
