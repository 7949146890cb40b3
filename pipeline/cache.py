"""The content-addressed cache folder.

Layout (``ROOT`` is ``--cache-dir``)::

    ROOT/entries/<stage>/<key>/manifest.json   written last; present = entry complete
                              /log.txt         the stage's log
                              /out/...         the outputs the stage returned
    ROOT/failed/<stage>/<key>/                 the last failure of that key: manifest + log
    ROOT/tmp/<stage>.<key>.<host>.<pid>.<n>/   entries being written (never read)
    ROOT/locks/<stage>/<key>                   one lock file per key (see locks.py)
    ROOT/refs/<workflow id>/<stage>/<item>.json  what each workflow slot last ran (for
                                               "why would it rerun" and stale status)
    ROOT/CACHEDIR.TAG                          written when the folder becomes a cache: the
                                               standard cache-directory tag (backup tools skip
                                               the folder), naming cobgs

An entry is written in ``tmp/`` with its manifest last, then renamed into ``entries/``
(one atomic rename on the same filesystem). A folder in ``entries/`` without a valid
manifest, or whose outputs are missing or changed size, is *corrupt*: reported, moved
away and recomputed. Nothing in ``tmp/`` is ever mistaken for a finished entry.

Commands that delete (``cache gc``, ``cache verify --fix``) first make the folder prove it is
a cache (:meth:`Cache.prove`: the tag, or for a cache an older cobgs wrote, an entry whose
manifest names its own key), and then touch only what has the shape this module gives its
files (:func:`entry_shape_problem`: ``<stage>/<64 hex digits>`` holding only an entry's
files); anything else under the folder is reported and left alone.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
import time
from dataclasses import dataclass
from itertools import count
from pathlib import Path
from typing import Any, Iterator, Optional

from .errors import CacheError
from .hashing import canonical_json, file_sha256, is_small, sha256_text
from .locks import EntryLock
from .publish import exchange_paths

MANIFEST = "manifest.json"
LOG = "log.txt"
OUT = "out"
SCRATCH = "scratch"
_serial = count()

#: Where a command finds the cache: ``--cache-dir``, else ``$COBGS_CACHE_DIR``, else ``./runs/cache``.
CACHE_ENV = "COBGS_CACHE_DIR"
DEFAULT_CACHE = Path("runs") / "cache"


def default_cache_dir(explicit: Optional[str] = None) -> Path:
    """The cache folder a command uses (:data:`CACHE_ENV`)."""
    if explicit:
        return Path(explicit)
    env = os.environ.get(CACHE_ENV)
    return Path(env) if env else DEFAULT_CACHE

#: The cache-directory tag (https://bford.info/cachedir/): its first line is the standard's
#: signature, so backup tools skip the folder; the second names cobgs, so a tag another tool
#: wrote proves nothing.
TAG = "CACHEDIR.TAG"
TAG_SIGNATURE = "Signature: 8a477f597d28d172789f06886806bc55"
TAG_TEXT = (f"{TAG_SIGNATURE}\n# This file is a cache directory tag created by cobgs: this folder is a cobgs "
            "pipeline cache.\n# `cobgs cache gc` and `cobgs cache verify --fix` remove only the entries it "
            "wrote here.\n# For information about cache directory tags, see https://bford.info/cachedir/\n")
#: The names the cache gives what it writes: a key is a sha256 in hex; a stage name is a
#: Python-like identifier (pipeline.stage.NAME_RE); an entry or failure record holds its
#: manifest, its log, its outputs and the task's scratch folder, nothing else.
KEY_RE = re.compile(r"^[0-9a-f]{64}$")
STAGE_RE = re.compile(r"^[a-z][a-z0-9_]*$")
ENTRY_FILES = frozenset({"manifest.json", "log.txt", "out", "scratch"})


@dataclass(frozen=True)
class EntryCheck:
    """Result of the cheap check of one key: ``state`` is done | absent | corrupt."""

    state: str
    manifest: Optional[dict] = None
    reason: str = ""


def write_json_atomic(path: Path, data: Any) -> None:
    """Write JSON to ``path`` through a temporary file and a rename (never half-written).

    No fsync: the guarantee is against the writer dying (SIGKILL, OOM, Ctrl-C), which the
    rename covers. After a power loss, ``cobgs cache verify --fix`` re-hashes everything
    (the cheap check already catches the usual symptom, truncated files).
    """
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{next(_serial)}.tmp")
    with open(tmp, "w", encoding="utf-8") as f:
        json.dump(data, f, indent=1, sort_keys=True, ensure_ascii=False)
    os.replace(tmp, path)


def read_json(path: Path) -> Any:
    with open(path, "rb") as f:
        return json.loads(f.read())


def read_json_object(path: Path) -> Optional[dict]:
    """A JSON object from ``path``; None when the file is missing, unreadable, not JSON or
    JSON of another shape (a list, a string ...): the cache treats all those as absent or
    corrupt, never as a crash."""
    try:
        data = read_json(path)
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def outputs_problem(outputs: Any) -> str:
    """What is wrong with a manifest's ``outputs`` table ("" when it has the shape written
    at commit: name -> {path: str, kind: file|dir, bytes: int, sizes: {rel: int}})."""
    if not isinstance(outputs, dict):
        return "outputs is not a table"
    for name, out in outputs.items():
        if not isinstance(out, dict) or not isinstance(out.get("path"), str):
            return f"output {name!r} has no path"
        if out.get("kind") not in ("file", "dir"):
            return f"output {name!r} has kind {out.get('kind')!r}"
        if out["kind"] == "file" and not isinstance(out.get("bytes"), int):
            return f"output {name!r} has no byte count"
        small = out.get("small")
        if small is not None and (not isinstance(small, dict)
                                  or not all(isinstance(v, str) for v in small.values())):
            return f"output {name!r} has a malformed list of small files"
        sizes = out.get("sizes")
        if out["kind"] == "dir" and sizes is not None and (
                not isinstance(sizes, dict) or not all(isinstance(v, int) for v in sizes.values())):
            return f"output {name!r} has a malformed file list"
    return ""


def inside(folder: Path, rel: Any) -> bool:
    """Whether ``rel`` (a path read from a manifest) names something inside ``folder``: a
    relative path without ``..`` that stays inside after symlinks are resolved. A shared
    cache (NFS, Ray) is written by other hosts and users: nothing it names is trusted."""
    if not isinstance(rel, str) or not rel or "\0" in rel:
        return False
    p = Path(rel)
    if p.is_absolute() or ".." in p.parts:
        return False
    base = os.path.realpath(folder)
    target = os.path.realpath(os.path.join(base, rel))
    return target == base or target.startswith(base + os.sep)


#: The manifest fields readers compute with, and what each must be where present: a JSON
#: value of another type (``"started": 1e300``, ``"host": {}``, ``"item": null``) makes the
#: entry corrupt, never a crash in ``status``, a summary or a report.
_SECONDS = ("started", "finished", "wall_s", "cpu_s", "cpu_children_s", "time")
_BYTES = ("peak_rss_bytes", "children_peak_rss_bytes", "gpu_peak_bytes")
_TEXTS = ("host", "stage", "device", "python", "package_version", "executor", "peak_rss_scope")
_MAX_SECONDS = 1e11  # (timestamps up to the year 5138; durations as long)


def _number(v: Any, hi: float) -> bool:
    import math

    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and 0 <= v <= hi


def fields_problem(manifest: dict) -> str:
    """What is wrong with the types of a manifest's fields ("" when nothing)."""
    for k in _SECONDS:
        if k in manifest and not _number(manifest[k], _MAX_SECONDS):
            return f"{k} is {manifest[k]!r}, not a number of seconds"
    for k in _BYTES:
        if manifest.get(k) is not None and not (_number(manifest[k], 2.0 ** 62) and isinstance(manifest[k], int)):
            return f"{k} is {manifest[k]!r}, not a byte count"
    for k in _TEXTS:
        if manifest.get(k) is not None and not isinstance(manifest[k], str):
            return f"{k} is {manifest[k]!r}, not a string"
    if manifest.get("node") is not None and not isinstance(manifest["node"], str):
        return f"node is {manifest['node']!r}, not a string"
    if "pid" in manifest and not (isinstance(manifest["pid"], int) and not isinstance(manifest["pid"], bool)):
        return f"pid is {manifest['pid']!r}, not a process id"
    if "version" in manifest and not isinstance(manifest["version"], (int, str)):
        return f"version is {manifest['version']!r}"
    for k in ("params", "dependencies"):
        if k in manifest and not isinstance(manifest[k], dict):
            return f"{k} is {manifest[k]!r}, not a table"
    if "item" in manifest:
        item = manifest["item"]
        if not isinstance(item, dict) or not isinstance(item.get("id"), str) \
                or not isinstance(item.get("values", {}), dict) or not isinstance(item.get("attrs", {}), dict):
            return f"item is {item!r}, not a table with an id"
    if "error" in manifest and not isinstance(manifest["error"], dict):
        return f"error is {manifest['error']!r}, not a table"
    return ""


def manifest_problem(manifest: Any, folder: Path) -> str:
    """What makes an entry's manifest untrustworthy ("" when nothing): fields of the wrong
    type (:func:`fields_problem`), a malformed ``outputs`` table, or a path (output, a file
    of an output folder, the log) that leaves the entry folder."""
    if not isinstance(manifest, dict):
        return "the manifest is not a JSON object"
    shape = fields_problem(manifest) or outputs_problem(manifest.get("outputs"))
    if shape:
        return shape
    for name, out in manifest["outputs"].items():
        if not inside(folder, out["path"]):
            return f"output {name!r} points outside its entry ({out['path']!r})"
        base = folder / out["path"]
        for table in ("sizes", "small"):
            for rel in (out.get(table) or {}):
                if not inside(base, rel):
                    return f"output {name!r} lists a file outside its entry ({rel!r})"
    if "log" in manifest and not inside(folder, manifest["log"]):
        return f"the log points outside its entry ({manifest['log']!r})"
    return ""


def entry_shape_problem(stage: str, key: str, folder: Path) -> str:
    """Why ``folder`` (``entries/<stage>/<key>`` or ``failed/...``) is not something the cache
    wrote ("" when it has an entry's shape): a stage name and a key of the cache's form, a real
    folder (no link) holding only an entry's files, and a manifest, where one is readable, that
    names this key. Deleting commands leave anything else alone."""
    if not STAGE_RE.match(stage):
        return f"{stage!r} is not a stage name"
    if not KEY_RE.match(key):
        return f"{key!r} is not a cache key (64 hex digits)"
    if folder.is_symlink() or not folder.is_dir():
        return "not a folder"
    try:
        names = set(os.listdir(folder))
    except OSError as exc:
        return f"cannot list it ({exc.strerror})"
    extra = sorted(names - ENTRY_FILES)
    if extra:
        return f"it holds {extra[:4]}, which no entry holds"
    m = read_json_object(folder / MANIFEST)
    if m is not None and "key" in m and m.get("key") != key:
        return f"its manifest names another key ({str(m.get('key'))[:16]!r})"
    return ""


class Cache:
    """A cache folder; every method is safe to call from several processes and hosts."""

    def __init__(self, root: os.PathLike | str):
        self.root = Path(os.path.abspath(os.fspath(root)))

    def ensure(self) -> None:
        try:
            for sub in ("entries", "failed", "tmp", "locks", "refs"):
                (self.root / sub).mkdir(parents=True, exist_ok=True)
            if not self.tagged():
                self._write_tag()
        except OSError as exc:
            raise CacheError(f"{self.root}: cannot create the cache folder: {exc}") from None
        if not os.access(self.root, os.W_OK):
            raise CacheError(f"{self.root}: the cache folder is not writable")

    # -- proof of being a cache (before anything is deleted) ---------------------------
    def tagged(self) -> bool:
        """Whether the folder carries the tag cobgs writes when it creates a cache."""
        try:
            with open(self.root / TAG, "rb") as f:
                head = f.read(4096).decode("utf-8", "replace")
        except OSError:
            return False
        return head.startswith(TAG_SIGNATURE) and "cobgs" in head

    def _write_tag(self) -> None:
        tmp = self.root / f".{TAG}.{os.getpid()}.{next(_serial)}.tmp"
        try:
            tmp.write_text(TAG_TEXT, encoding="utf-8")
            os.replace(tmp, self.root / TAG)
        finally:
            tmp.unlink(missing_ok=True)

    def prove(self) -> str:
        """Make sure the folder is a cobgs cache before a command deletes anything in it;
        returns how it was known ("tag", or "entry" for a cache an older cobgs wrote, which
        is then tagged).

        Raises:
            CacheError: the folder does not exist, has no ``entries/``, or carries no tag and
                has no entry whose manifest names its own key (a user's folder that happens to
                hold an ``entries/`` sub-folder): naming the folder; nothing was removed.
        """
        if not self.root.exists():
            raise CacheError(f"cache folder {self.root} does not exist")
        if not (self.root / "entries").is_dir():
            raise CacheError(f"cache folder {self.root} is not a cobgs cache (no entries/ folder)")
        if self.tagged():
            return "tag"
        for stage, key, folder in self.iter_entries():
            m = read_json_object(folder / MANIFEST)
            if not entry_shape_problem(stage, key, folder) and m is not None and m.get("key") == key \
                    and m.get("status") == "ok":
                try:  # a cache an older cobgs wrote, before the tag: tagged now
                    self._write_tag()
                except OSError:
                    pass
                return "entry"
        raise CacheError(f"{self.root} is not a cobgs cache: it has no {TAG} written by cobgs, and no folder "
                         "under entries/ is a cache entry (entries/<stage>/<64 hex digits>/manifest.json naming "
                         "that key); nothing was removed. Give the folder `cobgs run` wrote (--cache-dir)")

    # -- entries -----------------------------------------------------------------------
    def entry_dir(self, stage: str, key: str) -> Path:
        return self.root / "entries" / stage / key

    def failed_dir(self, stage: str, key: str) -> Path:
        return self.root / "failed" / stage / key

    def lock(self, stage: str, key: str) -> EntryLock:
        return EntryLock(self.root / "locks" / stage / key)

    def check(self, stage: str, key: str) -> EntryCheck:
        """Cheap validity check of an entry: its manifest and a stat of each output.

        Outputs are not re-hashed (their hash was taken when the entry was committed); a
        missing output file (inside folders too) or one whose size changed makes the entry
        corrupt. ``cache verify`` re-hashes everything.
        """
        folder = self.entry_dir(stage, key)
        try:
            raw = (folder / MANIFEST).read_bytes()
        except FileNotFoundError:
            if folder.exists():
                return EntryCheck("corrupt", reason="folder without manifest (interrupted "
                                                    "commit or manual edit)")
            return EntryCheck("absent")
        except OSError as exc:
            return EntryCheck("corrupt", reason=f"manifest unreadable: {exc}")
        try:
            manifest = json.loads(raw)
        except ValueError as exc:
            return EntryCheck("corrupt", reason=f"manifest is not valid JSON: {exc}")
        if not isinstance(manifest, dict) or manifest.get("key") != key \
                or manifest.get("status") != "ok" or not isinstance(manifest.get("outputs"), dict):
            return EntryCheck("corrupt", reason="manifest does not describe a finished entry "
                                                "with this key")
        shape = manifest_problem(manifest, folder)
        if shape:
            return EntryCheck("corrupt", reason=f"manifest is malformed: {shape}")
        for name, out in manifest["outputs"].items():
            try:
                st = os.stat(folder / out["path"])
            except OSError:
                return EntryCheck("corrupt", manifest, f"output {name!r} is missing")
            if out.get("kind") == "file" and st.st_size != out.get("bytes"):
                return EntryCheck("corrupt", manifest,
                                  f"output {name!r} changed size ({out.get('bytes')} -> "
                                  f"{st.st_size} bytes)")
            if out.get("kind") == "dir":
                base = folder / out["path"]
                if not os.path.isdir(base):
                    return EntryCheck("corrupt", manifest, f"output {name!r} is not a folder")
                for rel, size in (out.get("sizes") or {}).items():
                    try:
                        if os.stat(base / rel).st_size != size:
                            return EntryCheck("corrupt", manifest,
                                              f"output {name!r}: {rel} changed size")
                    except OSError:
                        return EntryCheck("corrupt", manifest,
                                          f"output {name!r}: {rel} is missing")
            # The small result files are re-hashed: a same-size edit is caught too.
            if out.get("kind") == "dir":
                pairs = [(folder / out["path"] / rel, sha, rel)
                         for rel, sha in (out.get("small") or {}).items()]
            elif is_small(out["path"], st.st_size):
                pairs = [(folder / out["path"], out.get("sha256"), out["path"])]
            else:
                pairs = []
            for path, sha, rel in pairs:
                try:
                    ok = file_sha256(path) == sha
                except OSError:
                    ok = False
                if not ok:
                    return EntryCheck("corrupt", manifest,
                                      f"output {name!r}: {rel} does not match the hash recorded "
                                      "when it was written (edited since?)")
        return EntryCheck("done", manifest)

    def load_failed(self, stage: str, key: str) -> Optional[dict]:
        """The failure record of a key; None when absent or unusable (not a JSON object, or
        fields of the wrong type)."""
        m = read_json_object(self.failed_dir(stage, key) / MANIFEST)
        return m if m is not None and not fields_problem(m) else None

    # -- writing (callers hold the entry's lock) ---------------------------------------
    def new_tmp(self, stage: str, key: str) -> Path:
        name = f"{stage}.{key}.{socket.gethostname()}.{os.getpid()}.{next(_serial)}"
        path = self.root / "tmp" / name
        path.mkdir(parents=True)
        return path

    def clean_tmp(self, stage: str, key: str) -> int:
        """Remove leftovers of killed writers of this key; only call under its lock."""
        return sum(1 for path in self.tmp_leftovers(stage, key)
                   if shutil.rmtree(path, ignore_errors=True) is None)

    def tmp_leftovers(self, stage: str, key: str) -> list[Path]:
        """Temporary folders of ``stage``/``key`` (a plain listing: glob would compile a
        pattern per key)."""
        prefix = f"{stage}.{key}."
        try:
            names = os.listdir(self.root / "tmp")
        except FileNotFoundError:
            return []
        return sorted(self.root / "tmp" / n for n in names if n.startswith(prefix))

    def _move_aside(self, path: Path) -> None:
        trash = self.root / "tmp" / f"trash.{path.name}.{os.getpid()}.{next(_serial)}"
        trash.parent.mkdir(exist_ok=True)  # (a cache whose tmp/ was deleted by hand)
        os.rename(path, trash)
        shutil.rmtree(trash, ignore_errors=True)

    def commit(self, tmp: Path, stage: str, key: str) -> Path:
        """Rename a finished ``tmp`` folder (manifest already written) into place."""
        final = self.entry_dir(stage, key)
        final.parent.mkdir(parents=True, exist_ok=True)
        if final.exists():  # corrupt leftover or a forced recompute
            # One atomic exchange: a kill at any moment leaves the old entry or the new one
            # (moving the old one aside first lost both to a kill between the two renames).
            if exchange_paths(tmp, final):
                shutil.rmtree(tmp, ignore_errors=True)  # now the old entry
                return final
            self._move_aside(final)
        os.rename(tmp, final)
        return final

    def remove_entry(self, stage: str, key: str) -> None:
        folder = self.entry_dir(stage, key)
        if folder.exists():
            self._move_aside(folder)

    #: What a failure record keeps of the task's outputs: the small JSON records it wrote at
    #: the top of its output folder (what it tried and found: a diagnosis), nothing else.
    FAILURE_KEEPS_BYTES = 1 << 20

    def record_failure(self, tmp: Path, stage: str, key: str, manifest: dict) -> Path:
        """Keep the log, a failure manifest and the task's small JSON records (its
        ``out/*.json`` up to :data:`FAILURE_KEEPS_BYTES` each) of ``tmp`` in ``failed/``;
        drop the other outputs."""
        keep = self.new_tmp(stage, key)
        if (tmp / LOG).exists():
            os.replace(tmp / LOG, keep / LOG)
        out = tmp / OUT
        if out.is_dir():
            for f in sorted(out.glob("*.json")):
                if f.is_file() and not f.is_symlink() and f.stat().st_size <= self.FAILURE_KEEPS_BYTES:
                    (keep / OUT).mkdir(exist_ok=True)
                    os.replace(f, keep / OUT / f.name)
        write_json_atomic(keep / MANIFEST, manifest)
        final = self.failed_dir(stage, key)
        final.parent.mkdir(parents=True, exist_ok=True)
        if final.exists():
            self._move_aside(final)
        os.rename(keep, final)
        shutil.rmtree(tmp, ignore_errors=True)
        return final

    def clear_failure(self, stage: str, key: str) -> None:
        folder = self.failed_dir(stage, key)
        if folder.exists():
            self._move_aside(folder)

    # -- per-workflow history ------------------------------------------------------------
    def ref_path(self, workflow_id: str, stage: str, item_id: str) -> Path:
        return (self.root / "refs" / workflow_id / stage
                / f"{sha256_text(item_id)[:20]}.json")

    def read_ref(self, workflow_id: str, stage: str, item_id: str) -> Optional[dict]:
        ref = read_json_object(self.ref_path(workflow_id, stage, item_id))
        return ref if ref is not None and isinstance(ref.get("key"), str) else None

    def write_ref(self, workflow_id: str, stage: str, item_id: str, ref: dict) -> None:
        path = self.ref_path(workflow_id, stage, item_id)
        path.parent.mkdir(parents=True, exist_ok=True)
        write_json_atomic(path, ref)

    def note_workflow(self, workflow_id: str, path: Path, name: str) -> None:
        folder = self.root / "refs" / workflow_id
        folder.mkdir(parents=True, exist_ok=True)
        info = {"path": os.fspath(path), "name": name}
        target = folder / "workflow.json"
        try:
            if read_json(target) == info:
                return
        except (OSError, ValueError):
            pass
        write_json_atomic(target, info)

    # -- listing -------------------------------------------------------------------------
    def iter_entries(self, kind: str = "entries") -> Iterator[tuple[str, str, Path]]:
        """``(stage, key, folder)`` of every folder under ``entries/`` (or ``failed/``)."""
        base = self.root / kind
        if not base.is_dir():
            return
        for stage_dir in sorted(base.iterdir()):
            if stage_dir.is_dir():
                for entry in sorted(stage_dir.iterdir()):
                    yield stage_dir.name, entry.name, entry


def ref_record(key: str, status: str, version: Any, params: Any, inputs: Any, device: str,
               item: str, data: Optional[dict] = None) -> dict:
    """What ``refs/`` remembers of a slot's last run (compared by ``--dry-run``)."""
    return {"key": key, "status": status, "version": version, "params": params,
            "inputs": inputs, "device": device, "item": item, "time": time.time(),
            "params_sha": sha256_text(canonical_json(params)), "data": data or {}}


def dir_size(path: Path) -> int:
    total = 0
    for root, _, files in os.walk(path):
        for name in files:
            try:
                total += os.lstat(os.path.join(root, name)).st_size
            except OSError:
                pass
    return total
