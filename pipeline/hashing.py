"""Content hashes: canonical JSON for keys, streamed sha256 for files and folders.

Output hashes are computed once, when an entry is committed, and stored in its manifest;
checking a cached entry later never re-reads the outputs (``cobgs cache verify`` does).
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

_CHUNK = 1 << 20
#: Files whose recorded hash is checked each time a cached entry is used (by a downstream
#: task, status, a report): the small result files a same-size edit could silently change.
SMALL_SUFFIXES = (".json", ".csv", ".npz", ".txt", ".toml")
SMALL_MAX_BYTES = 4 << 20


def is_small(name: str, size: int) -> bool:
    return name.lower().endswith(SMALL_SUFFIXES) and size <= SMALL_MAX_BYTES


def canonical_json(value: Any) -> str:
    """Deterministic JSON: sorted keys, no whitespace, UTF-8 kept as is."""
    return json.dumps(value, sort_keys=True, separators=(",", ":"), ensure_ascii=False,
                      allow_nan=False)


def sha256_text(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def file_sha256(path: Path) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


@dataclass(frozen=True)
class TreeHash:
    """Hash, total size and file count of a file or a folder."""

    sha256: str
    kind: str  # "file" | "dir"
    bytes: int
    files: int
    sizes: Optional[dict[str, int]] = None  # folder: relative file path -> bytes
    small: Optional[dict[str, str]] = None  # folder: relative path -> sha256 of small files


def tree_hash(path: Path) -> TreeHash:
    """sha256 of a file's bytes, or of a folder's sorted (relative path, kind, content) list.

    Symbolic links are hashed by their target text (not followed), so a link leaving the
    entry cannot make the hash depend on files outside it.
    """
    if path.is_symlink():
        return TreeHash(sha256_text("link:" + os.readlink(path)), "file", 0, 1)
    if path.is_file():
        return TreeHash(file_sha256(path), "file", path.stat().st_size, 1)
    if not path.is_dir():
        raise FileNotFoundError(f"{path}: not a file or folder")
    digest = hashlib.sha256(b"dir\n")
    total = files = 0
    sizes: dict[str, int] = {}
    small: dict[str, str] = {}
    for root, dirs, names in os.walk(path):
        dirs.sort()
        rel_root = os.path.relpath(root, path)
        for name in sorted(names + [d for d in dirs if os.path.islink(os.path.join(root, d))]):
            full = os.path.join(root, name)
            rel = os.path.normpath(os.path.join(rel_root, name)).replace(os.sep, "/")
            if os.path.islink(full):
                line = f"L {rel} {os.readlink(full)}\n"
            else:
                sha = file_sha256(Path(full))
                line = f"F {rel} {sha}\n"
                sizes[rel] = os.path.getsize(full)
                total += sizes[rel]
                if is_small(rel, sizes[rel]):
                    small[rel] = sha
            files += 1
            digest.update(line.encode("utf-8", "surrogateescape"))
        for d in dirs:
            if not os.path.islink(os.path.join(root, d)):
                rel = os.path.normpath(os.path.join(rel_root, d)).replace(os.sep, "/")
                digest.update(f"D {rel}\n".encode("utf-8", "surrogateescape"))
    return TreeHash(digest.hexdigest(), "dir", total, files, sizes, small)


#: Bounds of one fingerprint walk: a folder tree larger or deeper than this (a symlink to
#: "/", a network mount) is fingerprinted up to the bound, with a warning naming it.
FINGERPRINT_MAX_FILES = 1_000_000
FINGERPRINT_MAX_DEPTH = 40


def stat_fingerprint(path: Path, max_files: Optional[int] = None, max_depth: Optional[int] = None) -> str:
    """A cheap fingerprint of external data (a file or a folder tree): the sorted relative
    paths with each file's size and modification time, hashed. Nothing is read, so a
    dataset folder of thousands of images costs milliseconds; an edit, a replaced file or an
    added / removed one changes it (an edit that keeps size and mtime does not).

    Symlinked folders are followed once each: a link back into the tree (``-> .``, ``-> ..``)
    is recorded as a link, not walked again, and the walk stops at ``max_files`` files or
    ``max_depth`` levels (a link to ``/``), warning which folder it cut short."""
    return _fingerprint(path, max_files, max_depth, content=False)[0]


def content_fingerprint(path: Path, max_files: Optional[int] = None, max_depth: Optional[int] = None) -> str:
    """The same walk as :func:`stat_fingerprint` (links followed once, the same bounds), with
    each file's sha256 in place of its size and time: equal exactly when the bytes are, so a
    copy, a re-download or a re-mount of the same data keeps it. Reads every byte."""
    return _fingerprint(path, max_files, max_depth, content=True)[0]


def _fingerprint(path: Path, max_files: Optional[int], max_depth: Optional[int],
                 content: bool) -> tuple[str, bool, int]:
    """(fingerprint, whether the walk saw everything (no bound, no skipped link), bytes)."""
    import warnings

    max_files = FINGERPRINT_MAX_FILES if max_files is None else max_files
    max_depth = FINGERPRINT_MAX_DEPTH if max_depth is None else max_depth
    path = Path(path)
    try:
        st = path.stat()
    except OSError:
        return "missing", True, 0
    if not path.is_dir():
        if content:
            try:
                return sha256_text("content " + file_sha256(path)), True, st.st_size
            except OSError:
                return "missing", True, 0
        return sha256_text(f"{st.st_size} {st.st_mtime_ns}"), True, st.st_size
    total = 0
    rows: list[str] = []
    seen = {(st.st_dev, st.st_ino)}
    skipped: list[str] = []
    truncated = False
    for root, dirs, files in os.walk(path, followlinks=True):
        rel_root = Path(root).relative_to(path)
        depth = len(rel_root.parts)
        keep = []
        for d in sorted(dirs):
            full = os.path.join(root, d)
            try:
                ds = os.stat(full)
            except OSError:
                continue
            key = (ds.st_dev, ds.st_ino)
            rel = (rel_root / d).as_posix()
            if key in seen:  # a loop or a second link to a folder already walked
                rows.append(f"{rel}\tLINK-SEEN")
                skipped.append(rel)
            elif depth + 1 > max_depth:
                rows.append(f"{rel}\tTOO-DEEP")
                skipped.append(rel)
            else:
                seen.add(key)
                keep.append(d)
        dirs[:] = keep
        for name in sorted(files):
            p = Path(root) / name
            try:
                if content:
                    rows.append(f"{(rel_root / name).as_posix()}\t{file_sha256(p)}")
                else:
                    s = p.stat()
                    rows.append(f"{(rel_root / name).as_posix()}\t{s.st_size}\t{s.st_mtime_ns}")
                    total += s.st_size
            except OSError:
                continue
            if len(rows) >= max_files:
                truncated = True
                break
        if truncated:
            rows.append("TRUNCATED")
            break
    if (truncated or skipped) and not content:  # (the content walk follows a stat walk that warned)
        what = (f"stopped after {max_files} files" if truncated else "") + \
               ("; " if truncated and skipped else "") + \
               (f"did not follow {len(skipped)} linked or too-deep folder(s) such as {skipped[:3]}" if skipped else "")
        warnings.warn(f"fingerprint of {path}: {what} (symlink loops or links to large trees are "
                      "not walked; the fingerprint covers the rest)", RuntimeWarning, stacklevel=3)
    return (sha256_text(("content\n" if content else "") + "\n".join(rows)),
            not (truncated or skipped), total)


class FingerprintMemo:
    """What lets a key survive a copy of the same data: per external path, which content
    each stat fingerprint had (``by_stat``) and which fingerprint the keys first used for
    each content (``by_content``), in ``folder`` (the cache's ``fingerprints/``).

    :meth:`key` returns the stat fingerprint unless the same bytes were seen before under
    another one (the data re-mounted, copied without its times, re-downloaded), in which case
    it returns the one the cached entries were keyed with. The content is hashed only when
    a path's stat fingerprint is new to the memo; a read-only memo (status, reports) hashes
    only where a recorded content could match, and writes nothing. A lost update (two runs
    at once) costs at most a recomputation, as without the memo."""

    KEEP = 64  # entries per map and path (oldest dropped)
    #: Data this large (or a walk cut short: a link loop, a link to "/") is keyed by its
    #: stat fingerprint alone, as without the memo: hashing it would cost minutes.
    MAX_BYTES = 16 << 30

    def __init__(self, folder: os.PathLike | str, writable: bool):
        self.folder, self.writable = Path(folder), writable

    def _read(self, f: Path, where: str) -> tuple[dict, dict]:
        """(by_stat, by_content) of memo file ``f`` for path ``where``; empty for a missing,
        foreign or damaged file (anything but str -> str maps), which the next write replaces."""
        try:
            rec = json.loads(f.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return {}, {}
        if not isinstance(rec, dict) or rec.get("path") != where:
            return {}, {}
        maps = rec.get("by_stat"), rec.get("by_content")
        if not all(isinstance(m, dict) and all(isinstance(x, str) for kv in m.items() for x in kv) for m in maps):
            return {}, {}
        return dict(maps[0]), dict(maps[1])

    def key(self, path: Path, verify: bool = False, contents: Optional[dict] = None) -> str:
        """The fingerprint that keys ``path``'s data (see the class docstring).

        Args:
            verify: re-read the content even where the memo knows the stat fingerprint: an
                edit that kept size and modification time is then found, and the data get
                a fingerprint of their own (``--force`` of a stage that reads them,
                ``--verify-data``). A read-only memo returns what a verifying run would use
                without writing it.
            contents: a dict the caller keeps across memos of one command, so that data
                verified twice (a plan, then its run) are read once.
        """
        stat, complete, size = _fingerprint(path, None, None, content=False)
        if stat == "missing" or not complete or size > self.MAX_BYTES:
            return stat
        where = os.path.abspath(os.fspath(path))
        f = self.folder / (sha256_text(where)[:32] + ".json")
        by_stat, by_content = self._read(f, where)
        if not by_content and not self.writable and not verify:
            return stat  # nothing recorded: the plain stat fingerprint, without reading the data
        content = None if verify else by_stat.get(stat)
        changed = False
        if content is None:
            memo_key = (where, stat)
            content = contents.get(memo_key) if contents is not None else None
            if content is None:
                content = content_fingerprint(path)
                if contents is not None:
                    contents[memo_key] = content
            changed = by_stat.get(stat) != content
            by_stat[stat] = content
        fp = by_content.get(content)
        if fp is None:
            # New bytes: keyed by their stat fingerprint, unless other bytes already hold it
            # (an edit that kept size and time): then by stat and content together.
            fp = stat if stat not in by_content.values() else sha256_text(f"{stat}\ncontent {content}")
            by_content[content] = fp
            changed = True
        if changed and self.writable:
            def trim(d: dict) -> dict:  # insertion order is age: the file keeps it (no key sorting)
                return dict(list(d.items())[-self.KEEP:])

            text = json.dumps({"path": where, "by_stat": trim(by_stat), "by_content": trim(by_content)}, indent=1)
            tmp = f.with_name(f".{f.name}.{os.getpid()}.{id(self)}.tmp")
            try:  # through a rename: a reader never sees half a memo
                self.folder.mkdir(parents=True, exist_ok=True)
                tmp.write_text(text, encoding="utf-8")
                os.replace(tmp, f)
            except OSError:  # a memo that cannot be written only costs a recomputation later
                tmp.unlink(missing_ok=True)
        return fp
