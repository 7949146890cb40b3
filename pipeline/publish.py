"""Publish a folder as a whole: built beside its destination, then swapped into place.

``cobgs export`` and ``cobgs report`` write whole folders that a kill must never leave
half-new: :func:`publish_folder` builds the new folder as ``.<name>.tmp-<pid>`` next to
the destination and exchanges the two in one ``renameat2(RENAME_EXCHANGE)`` (Linux), so the
destination is at every moment either the previous folder or the new one. Where the
exchange is not available the old folder is first renamed to ``.<name>.old-<pid>``; a kill
between the two renames is repaired by the next publish (the old folder is put back).
Leftovers of killed publishers (their pid no longer alive) are removed by the next publish
to the same destination.
"""

from __future__ import annotations

import ctypes
import errno
import os
import re
import shutil
from pathlib import Path
from typing import Callable

from .errors import PipelineError

_AT_FDCWD = -100
_RENAME_EXCHANGE = 2


class DestinationError(PipelineError):
    """The destination cannot be replaced (not a folder, or a folder this tool did not write)."""


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def exchange_paths(a: Path, b: Path) -> bool:
    """Swap two paths atomically; False where the system cannot (then nothing changed)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        return False
    rc = fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE)
    if rc == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP):
        return False
    raise OSError(err, f"cannot exchange {a} and {b}: {os.strerror(err)}")


def clean_leftovers(dest: Path) -> None:
    """Remove what killed publishers left beside ``dest``; put an old folder back where a
    kill fell between the two renames of the fallback swap."""
    pat = re.compile(rf"^\.{re.escape(dest.name)}\.(tmp|old)-(\d+)$")
    if not dest.parent.is_dir():
        return
    for p in sorted(dest.parent.iterdir()):
        m = pat.match(p.name)
        if not m or _alive(int(m.group(2))):
            continue
        if m.group(1) == "old" and not dest.exists():
            os.rename(p, dest)
        else:
            shutil.rmtree(p, ignore_errors=True)


def publish_folder(dest: Path, write: Callable[[Path], None], marker: str, what: str) -> Path:
    """Build a folder with ``write(tmp)`` and put it at ``dest`` as a whole.

    Args:
        dest: the destination folder; it may be absent, empty, or a folder this tool wrote
            before (it holds ``marker``); anything else is refused.
        write: fills the (empty) temporary folder; it must write ``marker``.
        marker: the file name that identifies a folder this tool wrote.
        what: "report", "export" (for messages).

    Raises:
        DestinationError: ``dest`` is a file, or a non-empty folder without ``marker``.
    """
    dest = Path(os.path.abspath(dest))
    check_destination(dest, marker, what)
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.parent / f".{dest.name}.tmp-{os.getpid()}"
    old = dest.parent / f".{dest.name}.old-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        write(tmp)
        if not (tmp / marker).is_file():
            raise RuntimeError(f"internal: the {what} writer did not write {marker}")
        if not dest.exists():
            os.rename(tmp, dest)
        elif not exchange_paths(tmp, dest):
            shutil.rmtree(old, ignore_errors=True)
            os.rename(dest, old)
            os.rename(tmp, dest)
            tmp = old
        shutil.rmtree(tmp, ignore_errors=True)  # the previous folder
    except BaseException:
        if old.exists() and not dest.exists():
            os.rename(old, dest)  # interrupted between the fallback's two renames
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return dest


def check_destination(dest: Path, marker: str, what: str) -> None:
    """Refuse a destination that :func:`publish_folder` must not replace (call it early, to
    fail before the work); also cleans what killed publishers left beside it."""
    dest = Path(os.path.abspath(dest))
    clean_leftovers(dest)
    if dest.exists() and not dest.is_dir():
        raise DestinationError(f"{what} destination {dest} exists and is not a folder")
    if dest.is_dir() and any(dest.iterdir()) and not (dest / marker).is_file():
        raise DestinationError(f"{what} destination {dest} is a non-empty folder that this tool did not "
                               f"write (no {marker}); refusing to replace it: choose another folder")
