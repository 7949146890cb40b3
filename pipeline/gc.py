"""``cache gc``: remove what no given workflow references, never what a run is writing,
and never what the cache did not write (:func:`pipeline.cache.entry_shape_problem`): the
caller proves the folder is a cache first (:meth:`pipeline.cache.Cache.prove`)."""

from __future__ import annotations

import re
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

from .cache import KEY_RE, STAGE_RE, Cache, dir_size, entry_shape_problem
from .locks import pid_alive

TRASH_AGE_S = 600  # a trash folder older than this was left by a killed process


@dataclass
class GcReport:
    kept: int = 0
    removed: int = 0
    bytes: int = 0
    lines: list[str] = field(default_factory=list)
    #: what lies in the cache folder without the shape of something the cache wrote: left alone
    foreign: list[str] = field(default_factory=list)


#: ``tmp/`` names the cache gives: a task's folder ``<stage>.<key>.<host>.<pid>.<n>`` and a
#: folder moved aside before removal ``trash.<key>.<pid>.<n>``.
_TMP_TASK = re.compile(r"^([a-z][a-z0-9_]*)\.([0-9a-f]{64})\.[^/]+\.\d+\.\d+$")
_TMP_TRASH = re.compile(r"^trash\.[0-9a-f]{64}\.\d+\.\d+$")
_MEMO_TMP = re.compile(r"^\.[0-9a-f]{32}\.json\.\d+\.\d+\.tmp$")


def snapshot(cache_dir: Path) -> set[tuple[str, str, str]]:
    """What the cache holds now: ``(kind, stage, key)`` of every entry and failure record.
    Take it before working out what to keep, and pass it to :func:`collect`."""
    cache = Cache(cache_dir)
    return {(kind, stage, key) for kind in ("entries", "failed")
            for stage, key, _ in cache.iter_entries(kind)}


def collect(cache_dir: Path, keep: set[tuple[str, str]], dry_run: bool = False,
            existing: set[tuple[str, str, str]] | None = None) -> GcReport:
    """Remove entries and failure records not in ``keep``, stale temporary folders and
    unused lock files. Anything whose lock is held (being written) is left alone, and so is
    anything not in ``existing`` (a :func:`snapshot` taken before ``keep`` was worked
    out): a run beside gc may save an entry whose key ``keep`` could not know yet."""
    cache = Cache(cache_dir)
    report = GcReport()
    for kind in ("entries", "failed"):
        for stage, key, folder in list(cache.iter_entries(kind)):
            if (stage, key) in keep:
                report.kept += kind == "entries"
                continue
            why = entry_shape_problem(stage, key, folder)
            if why:
                report.foreign.append(f"{kind}/{stage}/{key} ({why})")
                continue
            lock = cache.lock(stage, key)
            if not lock.acquire(blocking=False):
                continue
            if existing is not None and (kind, stage, key) not in existing:
                lock.release()
                report.kept += kind == "entries"
                continue
            try:
                size = dir_size(folder)
                report.lines.append(f"{kind}/{stage}/{key[:12]} ({size} bytes)")
                report.removed += 1
                report.bytes += size
                if not dry_run:
                    shutil.rmtree(folder, ignore_errors=True)
            finally:
                lock.release(unlink=not dry_run)
    tmp_root = cache.root / "tmp"
    if tmp_root.is_dir():
        for folder in sorted(tmp_root.iterdir()):
            task = _TMP_TASK.match(folder.name)
            if folder.is_symlink() or not folder.is_dir():
                stale = False
            elif _TMP_TRASH.match(folder.name):
                stale = time.time() - folder.stat().st_mtime > TRASH_AGE_S
            elif task:
                lock = cache.lock(task.group(1), task.group(2))
                stale = lock.acquire(blocking=False)
                if stale:
                    lock.release()
            else:
                stale = False
            if not stale and not (task or _TMP_TRASH.match(folder.name)):
                report.foreign.append(f"tmp/{folder.name} (not a name the cache gives)")
            if stale:
                size = dir_size(folder)
                report.lines.append(f"tmp/{folder.name} ({size} bytes, left by a killed run)")
                report.removed += 1
                report.bytes += size
                if not dry_run:
                    shutil.rmtree(folder, ignore_errors=True)
    memo = cache.root / "fingerprints"
    if memo.is_dir():  # a memo write killed between its temporary file and the rename
        for f in sorted(memo.glob(".*.tmp")):
            if not _MEMO_TMP.match(f.name) or f.is_symlink() or not f.is_file():
                continue
            parts = f.name.split(".")
            pid = int(parts[-3]) if len(parts) >= 4 and parts[-3].isdigit() else 0
            try:
                old = time.time() - f.stat().st_mtime > TRASH_AGE_S
            except OSError:
                continue
            if old or not pid_alive(pid):
                size = f.stat().st_size if f.exists() else 0
                report.lines.append(f"fingerprints/{f.name} ({size} bytes, left by a killed run)")
                report.removed += 1
                report.bytes += size
                if not dry_run:
                    f.unlink(missing_ok=True)
    locks_root = cache.root / "locks"
    if locks_root.is_dir() and not dry_run:
        for path in sorted(locks_root.glob("*/*")):
            if not (STAGE_RE.match(path.parent.name) and KEY_RE.match(path.name)) \
                    or path.is_symlink() or not path.is_file():
                report.foreign.append(f"locks/{path.parent.name}/{path.name} (not a lock file of the cache)")
                continue
            lock = cache.lock(path.parent.name, path.name)
            if lock.acquire(blocking=False):
                lock.release(unlink=True)
    return report

