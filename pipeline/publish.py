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
list (a user's notes saved into an export), unless the caller passes ``replace``. A folder
an older cobgs wrote, whose marker lists no files, cannot tell the user's files from ours:
it is replaced only with ``replace``.

The builds take minutes, so the destination is checked three times: before the work (the
caller), just before the exchange, and after it, on the previous folder, which is swapped
back if something the marker does not list appeared in it meanwhile. One publisher at a time
holds a destination (a lock file ``.<name>.publish-lock`` beside it, gone when it finishes);
another is refused at once, naming the holder. A destination that is a mount point (a Docker
volume, a USB drive's root) cannot be renamed: its content is swapped entry by entry inside
it instead (:func:`_swap_inside`), with a journal that the next publish uses to finish or
undo a swap a kill interrupted.
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
from .locks import EntryLock, pid_alive

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
    if dest.is_dir() and not dest.is_symlink():
        for p in sorted(dest.iterdir()):
            m = _INSIDE.match(p.name)
            if m and m.group(1) and p.is_dir() and not p.is_symlink() and not pid_alive(int(m.group(1))):
                _recover_inside(dest, p)


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
    """``(paths, legacy)`` this tool wrote into the folder according to its marker ``rec``, or
    None when ``rec`` is no marker of ``cobgs <what>``. ``legacy``: the marker has the shape an
    older cobgs gave it, which lists folders, not files, so the user's files in them cannot be
    told apart (replaced only with ``replace``)."""
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


#: What a publisher keeps inside a destination it swaps entry by entry (a mount point): its
#: work folder ``.cobgs-<what>.swap-<pid>`` and its lock file; never one of the user's files.
_INSIDE = re.compile(r"^\.cobgs-(?:(?:report|export)\.swap-(\d+)|publish-lock)$")
_INSIDE_LOCK = ".cobgs-publish-lock"


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


def foreign_files(dest: Path, expected: set[str], subtrees: bool = False) -> list[str]:
    """What lies in ``dest`` that the marker's list does not account for (the user's own
    files); ``subtrees``: a listed path covers everything below it."""
    out = []
    for rel in _walk(dest):
        path = rel.rstrip("/")
        parts = path.split("/")
        if path in expected or _INSIDE.match(parts[0]):
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
        DestinationError: see :func:`check_destination`; also another publisher holding the
            destination, something the checks refuse appearing while the folder was built,
            and a full disk (one line each; the destination is left as it was).
    """
    dest = Path(os.path.abspath(dest))
    check_destination(dest, marker, what, replace=replace)
    try:
        dest.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DestinationError(f"{what} destination {dest}: cannot create {dest.parent}: {exc.strerror}") from None
    # a mount point cannot be renamed (and its parent may not be writable: a USB drive's root); the
    # current folder (`--to .`) must stay the same folder for this process and the user's shell
    inside = is_mount_point(dest) or _holds_cwd(dest)
    lock = EntryLock(dest / _INSIDE_LOCK if inside else dest.parent / f".{dest.name}.publish-lock")
    try:
        if not lock.acquire(blocking=False):
            raise DestinationError(f"{what} destination {dest} is being written by another cobgs process "
                                   f"({lock.holder()}); wait for it to finish, or choose another folder")
    except OSError as exc:
        raise DestinationError(f"{what} destination {dest}: cannot lock it ({exc.strerror}); is "
                               f"{dest.parent} writable?") from None
    try:
        check_destination(dest, marker, what, replace=replace)  # (a publisher that held the lock until now)
        tmp = (dest / f".cobgs-{what}.swap-{os.getpid()}" / "new") if inside \
            else dest.parent / f".{dest.name}.tmp-{os.getpid()}"
        try:
            shutil.rmtree(tmp, ignore_errors=True)
            tmp.mkdir(parents=True)
            try:
                write(tmp)
                _stamp(tmp / marker, tmp, what)
                # the build took minutes: what the destination holds now is checked again
                check_destination(dest, marker, what, replace=replace)
                if inside:
                    _swap_inside(dest, tmp.parent, marker, what, replace)
                else:
                    _swap(dest, tmp, marker, what, replace)
            finally:
                shutil.rmtree(tmp.parent if inside else tmp, ignore_errors=True)
        except OSError as exc:
            if exc.errno == errno.ENOSPC:
                raise DestinationError(f"{what} destination {dest}: no space left on the device while writing "
                                       f"the {what} (needs more free space there, or another folder); {dest} was "
                                       "left as it was") from None
            raise
    finally:
        lock.release(unlink=True)
    return dest


def _swap(dest: Path, tmp: Path, marker: str, what: str, replace: bool) -> None:
    """Put the finished folder ``tmp`` at ``dest`` in one exchange (or two renames where the
    system has no exchange); the previous folder is checked once more after the exchange and
    swapped back if it holds what its marker does not list (written during the exchange)."""
    old = dest.parent / f".{dest.name}.old-{os.getpid()}"
    if not dest.exists():
        try:
            os.rename(tmp, dest)
            return
        except OSError as exc:  # something appeared at dest meanwhile: exchange and check it
            if exc.errno not in (errno.ENOTEMPTY, errno.EEXIST):
                raise
    if exchange_paths(tmp, dest):
        problem = _still_replaceable(tmp, marker, what, replace)
        if problem:
            exchange_paths(tmp, dest)  # swap back: the previous folder stays, the new one goes
            raise DestinationError(f"{what} destination {dest}: {problem}; it was left as it was")
        return  # tmp is now the previous folder (the caller removes it)
    shutil.rmtree(old, ignore_errors=True)
    os.rename(dest, old)
    try:
        problem = _still_replaceable(old, marker, what, replace)
        if problem:
            raise DestinationError(f"{what} destination {dest}: {problem}; it was left as it was")
        os.rename(tmp, dest)
    except BaseException:
        if not dest.exists():
            os.rename(old, dest)  # interrupted between the two renames, or refused
        raise
    shutil.rmtree(old, ignore_errors=True)


def _still_replaceable(folder: Path, marker: str, what: str, replace: bool) -> str:
    """"" when the previous folder, moved aside, holds only what its marker lists (or
    nothing; anything of ours with ``replace``); else what was found."""
    try:
        if not any(folder.iterdir()):
            return ""
    except OSError:
        return ""
    rec = _read_marker(folder / marker) if (folder / marker).is_file() else None
    known = _expected_files(rec, what, marker) if rec is not None else None
    if known is None:
        return f"files appeared in it while the {what} was built ({_walk(folder)[:_NAMED]})"
    if known[1] and not replace:
        return f"it became a folder of an older cobgs while the {what} was built"
    extra = foreign_files(folder, known[0], known[1])
    if extra and not replace:
        return f"files cobgs did not write appeared in it while the {what} was built: {extra[:_NAMED]}"
    return ""


# -- destinations that are mount points ------------------------------------------------------
def is_mount_point(path: Path) -> bool:
    """Whether ``path`` is a mount point (a bind mount from the same filesystem included,
    which :func:`os.path.ismount` misses: Docker volumes are those)."""
    if not path.is_dir():
        return False
    if os.path.ismount(path):
        return True
    real = os.path.realpath(path)
    try:
        with open("/proc/self/mountinfo", encoding="utf-8", errors="replace") as f:
            for line in f:
                fields = line.split()
                if len(fields) > 4 and _unescape(fields[4]) == real:
                    return True
    except OSError:
        pass
    return False


def _holds_cwd(path: Path) -> bool:
    """Whether the current folder is ``path`` or lies inside it."""
    try:
        cwd = os.path.realpath(os.getcwd())
    except OSError:
        return False
    real = os.path.realpath(path)
    return path.is_dir() and (cwd == real or cwd.startswith(real.rstrip(os.sep) + os.sep))


def _unescape(text: str) -> str:
    """A mountinfo path field: spaces, tabs, newlines and backslashes are octal escapes."""
    return re.sub(r"\\([0-7]{3})", lambda m: chr(int(m.group(1), 8)), text)


def _swap_inside(dest: Path, work: Path, marker: str, what: str, replace: bool) -> None:
    """Swap the content of a mount point ``dest`` for ``work/new``, entry by entry on its own
    filesystem: the previous entries the marker lists go to ``work/old``, the new ones come in,
    the marker last. ``work/journal.json`` (written first) names both sets, so a kill at any step
    is finished or undone by the next publish (:func:`_recover_inside`)."""
    new = work / "new"
    old_rec = _read_marker(dest / marker) if (dest / marker).is_file() else None
    known = _expected_files(old_rec, what, marker) if old_rec is not None else None
    theirs = [n for n in sorted(os.listdir(dest)) if not _INSIDE.match(n)]
    if known is not None:
        owned = {f.split("/")[0] for f in known[0]}
        theirs_not_ours = [n for n in theirs if n not in owned]
        if theirs_not_ours and not replace:  # (check_destination names them; a last look)
            raise DestinationError(f"{what} destination {dest} holds {theirs_not_ours[:_NAMED]}, which cobgs did not "
                                   "write; it was left as it was")
    elif theirs:
        raise DestinationError(f"{what} destination {dest} holds {theirs[:_NAMED]}, which cobgs did not write; "
                               "it was left as it was")
    moving_out = [n for n in theirs if n != marker] + ([marker] if marker in theirs else [])
    moving_in = [n for n in sorted(os.listdir(new)) if n != marker] + [marker]
    journal = {"marker": marker, "out": moving_out, "in": moving_in,
               "new_marker": (new / marker).read_text(encoding="utf-8")}
    tmp_journal = work / "journal.json.tmp"
    tmp_journal.write_text(json.dumps(journal), encoding="utf-8")
    os.replace(tmp_journal, work / "journal.json")
    (work / "old").mkdir(exist_ok=True)
    try:
        # the marker leaves first (a half-swapped folder never claims to be a finished one) ...
        for name in ([marker] if marker in moving_out else []) + [n for n in moving_out if n != marker]:
            os.rename(dest / name, work / "old" / name)
        # ... and comes in last
        for name in moving_in:
            os.rename(new / name, dest / name)
    except BaseException:
        _recover_inside(dest, work)  # undone: the previous content is back in place
        raise


def _recover_inside(dest: Path, work: Path) -> None:
    """Finish or undo a swap inside a mount point that a kill interrupted (its pid is dead):
    when the marker in place is the new one, the swap was complete; otherwise the new entries
    that came in go back out and the previous ones come back."""
    journal = None
    try:
        journal = json.loads((work / "journal.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        pass
    if isinstance(journal, dict) and isinstance(journal.get("marker"), str):
        marker = journal["marker"]
        try:
            done = (dest / marker).read_text(encoding="utf-8") == journal.get("new_marker")
        except OSError:
            done = False
        if not done:
            for name in journal.get("in") or []:
                if isinstance(name, str) and not _INSIDE.match(name) and "/" not in name \
                        and (dest / name).exists() and not (work / "new" / name).exists():
                    target = dest / name
                    shutil.rmtree(target) if target.is_dir() and not target.is_symlink() else target.unlink()
            for name in journal.get("out") or []:
                if isinstance(name, str) and "/" not in name and (work / "old" / name).exists() \
                        and not (dest / name).exists():
                    os.rename(work / "old" / name, dest / name)
    shutil.rmtree(work, ignore_errors=True)


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


def check_apart(dest: Path, cache: Path, what: str) -> None:
    """Refuse a destination inside the cache folder (``<cache>/tmp`` is the cache's to clean) or
    one that holds the cache (replacing it would take the cache with it).

    Raises:
        DestinationError: naming both folders.
    """
    d, c = os.path.realpath(dest), os.path.realpath(cache)
    if d == c or d.startswith(c.rstrip(os.sep) + os.sep):
        raise DestinationError(f"{what} destination {dest} lies inside the cache folder {cache}, which `cobgs run` and "
                               "`cobgs cache gc` manage; choose a folder outside it")
    if c.startswith(d.rstrip(os.sep) + os.sep):
        raise DestinationError(f"{what} destination {dest} holds the cache folder {cache}: replacing it would take the "
                               "cache with it; choose another folder")


def check_destination(dest: Path, marker: str, what: str, replace: bool = False) -> None:
    """Refuse a destination that :func:`publish_folder` must not replace (call it early, to
    fail before the work); also cleans what killed publishers left beside it.

    Accepted: an absent or empty folder, or a folder whose ``marker`` this tool wrote (its
    ``generator`` is "cobgs <what>" and it names its workflow) and that holds nothing the
    marker does not list; with ``replace``, such a folder even where the user added files,
    and a folder an older cobgs wrote (its marker lists no files).

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
    if not dest.is_dir() or not any(not _INSIDE.match(p.name) for p in dest.iterdir()):
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
    if known[1] and not replace:
        n = len(_walk(dest))
        raise DestinationError(f"{what} destination {dest} is {'an' if what[0] in 'aeiou' else 'a'} {what} of an older cobgs, whose {marker} does not list "
                               f"its files, so cobgs cannot tell files you added from its own ({n} files and folders "
                               f"there); pass --replace to replace the folder with everything in it, or choose "
                               "another folder")
    extra = foreign_files(dest, *known)
    if extra and not replace:
        more = f" and {len(extra) - _NAMED} more" if len(extra) > _NAMED else ""
        raise DestinationError(f"{what} destination {dest} is an earlier {what} of cobgs, but it also holds files "
                               f"that `{generator_name(what)}` did not write: {extra[:_NAMED]}{more}; move them "
                               f"out, or pass --replace to replace the folder with them")
