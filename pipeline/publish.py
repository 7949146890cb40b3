"""Publish a folder as a whole: built beside its destination, then swapped into place.

``cobgs export`` and ``cobgs report`` write whole folders that a kill must never leave
half-new: :func:`publish_folder` builds the new folder as ``.<name>.tmp-<pid>`` next to
the destination and exchanges the two in one ``renameat2(RENAME_EXCHANGE)`` (Linux), so the
destination is at every moment either the previous folder or the new one. Where the
exchange is not available the old folder is first renamed to ``.<name>.old-<pid>``; a kill
between the two renames is repaired by the next publish (the old folder is put back).
Leftovers of killed publishers (their pid no longer alive) are removed by the next publish
to the same destination.

A destination is replaced only when it is absent, empty, or a folder this module published:
its marker file (``report.json``, ``export.json``) names the generator (``"cobgs report"``)
and the workflow, and lists every file written (``files``). A marker of any other content is
refused, naming the file, and so is a folder of ours that holds files the marker does not
list (a user's notes saved into an export), unless the caller passes ``replace``.
"""

from __future__ import annotations

import ctypes
import errno
import json
import os
import re
import shutil
from pathlib import Path
from typing import Callable, Optional

from .errors import PipelineError
from .locks import pid_alive

_AT_FDCWD = -100
_RENAME_EXCHANGE = 2


class DestinationError(PipelineError):
    """The destination cannot be replaced (not a folder, or a folder this tool did not write)."""


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
        if not m or pid_alive(int(m.group(2))):
            continue
        if m.group(1) == "old" and not dest.exists():
            os.rename(p, dest)
        else:
            shutil.rmtree(p, ignore_errors=True)


def generator_name(what: str) -> str:
    """What a marker's ``generator`` field says for a folder of ``what`` ("report", "export")."""
    return f"cobgs {what}"


#: Folders written before markers carried ``generator`` / ``files`` are recognised by the exact
#: shape their writer gave the marker (and, for a report, its fixed top-level layout), so an
#: existing report or export can still be replaced; nothing else is.
_LEGACY_REPORT_TOP = frozenset({"index.html", "static", "img", "plots", "logs", "workflow.toml", "report.json",
                                "data", "tables.md"})
_LEGACY_EXPORT_KEYS = frozenset({"workflow", "cache_dir", "copied", "missing"})
#: How many stray files a refusal names.
_NAMED = 6


def _read_marker(path: Path) -> Optional[dict]:
    try:
        with open(path, "rb") as f:
            raw = f.read(64 << 20)
        rec = json.loads(raw.decode("utf-8"))
    except (OSError, ValueError, RecursionError):
        return None
    return rec if isinstance(rec, dict) else None


def _expected_files(rec: dict, what: str, marker: str) -> Optional[tuple[set[str], bool]]:
    """``(paths, whole_subtrees)`` this tool wrote into the folder according to its marker
    ``rec``, or None when ``rec`` is no marker of ``cobgs <what>``. ``whole_subtrees``: a
    listed path covers everything below it (the legacy layouts, which listed folders)."""
    workflow = rec.get("workflow")
    if rec.get("generator") == generator_name(what):
        files = rec.get("files")
        if not isinstance(workflow, str) or not workflow or not isinstance(files, list) \
                or not all(isinstance(f, str) for f in files):
            return None
        return set(files) | {marker}, False
    if what == "report" and rec.get("format") == "cobgs-report" and isinstance(workflow, str) and workflow:
        return set(_LEGACY_REPORT_TOP), True
    if what == "export" and set(rec) == _LEGACY_EXPORT_KEYS and isinstance(workflow, str) and workflow \
            and isinstance(rec.get("copied"), list) \
            and all(isinstance(c, dict) and isinstance(c.get("file"), str) for c in rec["copied"]):
        return {c["file"] for c in rec["copied"]} | {marker}, True
    return None


def _walk(root: Path) -> list[str]:
    """Every file, link and empty folder under ``root``, relative, sorted (links not followed)."""
    out = []
    for base, dirs, names in os.walk(root):
        rel = Path(base).relative_to(root)
        for d in list(dirs):
            if os.path.islink(os.path.join(base, d)):
                names.append(d)
                dirs.remove(d)
        if not names and not dirs and rel.parts:
            out.append(rel.as_posix() + "/")
        out += [(rel / n).as_posix() for n in names]
    return sorted(out)


def foreign_files(dest: Path, expected: set[str], subtrees: bool) -> list[str]:
    """What lies in ``dest`` that the marker's list does not account for (the user's own files)."""
    out = []
    for rel in _walk(dest):
        path = rel.rstrip("/")
        parts = path.split("/")
        if path in expected:
            continue
        if subtrees and any("/".join(parts[:i]) in expected for i in range(1, len(parts))):
            continue
        if rel.endswith("/") and any(e.startswith(path + "/") for e in expected):
            continue  # an empty folder the tool wrote
        out.append(rel)
    return out


def publish_folder(dest: Path, write: Callable[[Path], None], marker: str, what: str,
                   replace: bool = False) -> Path:
    """Build a folder with ``write(tmp)`` and put it at ``dest`` as a whole.

    Args:
        dest: the destination folder; it may be absent, empty, or a folder this tool wrote
            before (:func:`check_destination`); anything else is refused.
        write: fills the (empty) temporary folder; it must write ``marker``, a JSON object
            with a ``workflow`` field. This function adds ``generator`` ("cobgs <what>") and
            ``files`` (every file written, relative), which is how a later publish knows the
            folder as its own and tells a user's added files apart.
        marker: the file name that identifies a folder this tool wrote.
        what: "report", "export" (for messages and the ``generator`` field).
        replace: also replace a folder of this tool that holds files the user added.

    Raises:
        DestinationError: see :func:`check_destination`.
    """
    dest = Path(os.path.abspath(dest))
    check_destination(dest, marker, what, replace=replace)
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.parent / f".{dest.name}.tmp-{os.getpid()}"
    old = dest.parent / f".{dest.name}.old-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        write(tmp)
        _stamp(tmp / marker, tmp, what)
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


def _stamp(path: Path, root: Path, what: str) -> None:
    """Add ``generator`` and ``files`` to the marker the writer wrote."""
    rec = _read_marker(path) if path.is_file() else None
    if rec is None or not isinstance(rec.get("workflow"), str):
        raise RuntimeError(f"internal: the {what} writer did not write {path.name} as a JSON object "
                           "with a 'workflow' field")
    files = [f for f in _walk(root) if not f.endswith("/")]
    rec = {"generator": generator_name(what), **{k: v for k, v in rec.items() if k != "generator"},
           "files": files}
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(rec, indent=1, default=str) + "\n", encoding="utf-8")
    os.replace(tmp, path)


def check_destination(dest: Path, marker: str, what: str, replace: bool = False) -> None:
    """Refuse a destination that :func:`publish_folder` must not replace (call it early, to
    fail before the work); also cleans what killed publishers left beside it.

    Accepted: an absent or empty folder, or a folder whose ``marker`` this tool wrote (its
    ``generator`` is "cobgs <what>" and it names its workflow) and that holds nothing the
    marker does not list; with ``replace``, such a folder even where the user added files.

    Raises:
        DestinationError: naming the destination and why: a file on the way, a symlink,
            a folder without the marker, a marker this tool did not write, or the files the
            user added.
    """
    dest = Path(os.path.abspath(dest))
    if dest.is_symlink():  # the swap would replace the link, not the folder it points to
        raise DestinationError(f"{what} destination {dest} is a symbolic link; give the folder itself "
                               f"({os.path.realpath(dest)}) or another path")
    for p in (dest, *dest.parents):
        if p.exists() and not p.is_dir():
            where = "exists and is not a folder" if p == dest else f"lies under {p}, which is a file, not a folder"
            raise DestinationError(f"{what} destination {dest} {where}: choose another path")
    clean_leftovers(dest)
    if not dest.is_dir() or not any(dest.iterdir()):
        return
    mark = dest / marker
    if not mark.is_file():
        have = sorted(p.name for p in dest.iterdir())[:_NAMED]
        raise DestinationError(f"{what} destination {dest} is a non-empty folder that this tool did not "
                               f"write (no {marker}; it holds {have}); refusing to replace it: choose another folder")
    rec = _read_marker(mark)
    known = _expected_files(rec, what, marker) if rec is not None else None
    if known is None:
        raise DestinationError(f"{what} destination {dest}: {mark} was not written by `{generator_name(what)}` "
                               f"(a {marker} of cobgs names its generator, {generator_name(what)!r}, and its "
                               "workflow); refusing to replace the folder: choose another folder")
    extra = foreign_files(dest, *known)
    if extra and not replace:
        more = f" and {len(extra) - _NAMED} more" if len(extra) > _NAMED else ""
        raise DestinationError(f"{what} destination {dest} is an earlier {what} of cobgs, but it also holds files "
                               f"that `{generator_name(what)}` did not write: {extra[:_NAMED]}{more}; move them "
                               f"out, or pass --replace to replace the folder with them")
