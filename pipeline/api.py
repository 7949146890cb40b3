"""Read API for commands that present results (``cobgs report``, ``cobgs export``).

    from pipeline import Cache, entries, load_workflow
    wf = load_workflow("workflows/demo.toml", registry)
    for rec in entries(wf, cache_dir):          # every (item, stage), plan order
        if rec.state == "done":
            ply = rec.output("scene")             # path of a finished artifact
            rec.manifest["wall_s"], rec.manifest["params"], ...
        elif rec.state == "failed":
            rec.log_path, rec.manifest["error"]["summary"]

Nothing is run or written. Inside a stage, ``entry_of(inputs["metrics"][item])`` finds
the entry an input came from, ``load_manifest`` reads it and ``upstream_entries`` walks
the provenance one step up (a report stage can collect every stage's timings this way). ``rec.state`` is done | failed | corrupt | stale | missing
(see :class:`pipeline.plan.TaskState`); ``rec.manifest`` is the entry's manifest for done
records and the failure manifest for failed ones.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Union

from .cache import MANIFEST, Cache, read_json
from .plan import Plan, TaskState, inspect
from .workflow import Workflow


def entries(workflow: Workflow, cache: Union[Cache, os.PathLike, str]) -> list[TaskState]:
    """The state of every task of ``workflow`` in ``cache``, with manifests and reasons."""
    cache = cache if isinstance(cache, Cache) else Cache(cache)
    return inspect(Plan(workflow), cache)


def load_manifest(entry_dir: Union[os.PathLike, str]) -> dict:
    """The manifest of an entry (or failure record) folder."""
    return read_json(Path(entry_dir) / MANIFEST)


def entry_of(artifact: Union[os.PathLike, str]) -> Path:
    """The entry folder holding an artifact path (e.g. one a stage received as input), so
    a stage can read the manifest of what it was given (timings, params, provenance)."""
    path = Path(os.path.abspath(os.fspath(artifact)))
    for folder in (path, *path.parents):
        if (folder / MANIFEST).is_file() and folder.parent.parent.name == "entries":
            return folder
    raise FileNotFoundError(f"{artifact}: not inside a pipeline cache entry")


def upstream_entries(entry_dir: Union[os.PathLike, str]) -> dict[str, Union[Path, dict]]:
    """The entry folders an entry was computed from, per input artifact (fan-in inputs as
    ``{item id: folder}``), read from its manifest: the provenance chain, one step up."""
    entry_dir = Path(entry_dir)
    cache = Cache(entry_dir.parents[2])
    out: dict[str, Union[Path, dict]] = {}
    for name, rec in load_manifest(entry_dir).get("inputs", {}).items():
        if "items" in rec:
            out[name] = {item: cache.entry_dir(rec["stage"], r["key"])
                         for item, r in rec["items"].items()}
        else:
            out[name] = cache.entry_dir(rec["stage"], rec["key"])
    return out
