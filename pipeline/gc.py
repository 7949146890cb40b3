"""``cache gc``: remove what no given workflow references, never what a run is writing."""

from __future__ import annotations

import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

from .cache import Cache, dir_size
from .locks import pid_alive

TRASH_AGE_S = 600  # a trash folder older than this was left by a killed process


@dataclass
class GcReport:
    kept: int = 0
    removed: int = 0
    bytes: int = 0
    lines: list[str] = field(default_factory=list)


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
            parts = folder.name.split(".")
            if parts[0] == "trash":
                stale = time.time() - folder.stat().st_mtime > TRASH_AGE_S
            elif len(parts) >= 3:
                lock = cache.lock(parts[0], parts[1])
                stale = lock.acquire(blocking=False)
                if stale:
                    lock.release()
            else:
                stale = False
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
            lock = cache.lock(path.parent.name, path.name)
            if lock.acquire(blocking=False):
                lock.release(unlink=True)
    return report

