"""Writes that readers never see half done: a file (or a folder) is built under a temporary
name beside its destination and renamed into place; on any error, Ctrl-C included, the
temporary is removed and the destination is untouched. One helper for every artifact the
library writes (PLYs, checkpoints, Adam moments, masks, JSON logs, model manifests,
generated scenes, SfM results)."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path
from typing import Callable, IO


def write_atomic(path: os.PathLike | str, write: Callable[[IO[bytes]], None]) -> Path:
    """Create ``path`` through ``write(file)`` (a binary file open on a temporary sibling),
    then rename it into place."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def write_bytes_atomic(path: os.PathLike | str, data: bytes | memoryview) -> Path:
    return write_atomic(path, lambda f: f.write(data))


def write_text_atomic(path: os.PathLike | str, text: str) -> Path:
    return write_bytes_atomic(path, text.encode("utf-8"))


def build_folder_atomic(out: os.PathLike | str, build: Callable[[Path], None]) -> Path:
    """Create folder ``out`` through ``build(tmp)`` (an empty temporary sibling folder), then
    put it in place as a whole: an existing ``out`` is replaced only once the new one is
    complete (moved aside, swapped, removed)."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    try:
        build(tmp)
        if out.exists():
            trash = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
            os.replace(out, trash / "old")
            os.replace(tmp, out)
            shutil.rmtree(trash, ignore_errors=True)
        else:
            os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out
