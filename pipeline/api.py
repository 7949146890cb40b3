"""Read API for commands that present results (``cobgs report``, ``cobgs export``).

    from pipeline import Cache, entries, load_workflow
    wf = load_workflow("workflows/demo.toml", registry)
    for rec in entries(wf, cache_dir):          # every (item, stage), plan order
        if rec.state == "done":
            ply = rec.output("scene")             # path of a finished artifact
            rec.manifest["wall_s"], rec.manifest["params"], ...
        elif rec.state == "failed":
            rec.log_path, rec.manifest["error"]["summary"]

Nothing is run or written. ``rec.state`` is done | failed | corrupt | stale | missing
(see :class:`pipeline.plan.TaskState`); ``rec.manifest`` is the entry's manifest for done
records and the failure manifest for failed ones.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Union

from .cache import Cache
from .plan import Plan, TaskState, inspect
from .workflow import Workflow


def entries(workflow: Workflow, cache: Union[Cache, os.PathLike, str]) -> list[TaskState]:
    """The state of every task of ``workflow`` in ``cache``, with manifests and reasons."""
    cache = cache if isinstance(cache, Cache) else Cache(cache)
    return inspect(Plan(workflow), cache)


def load_manifest(entry_dir: Union[os.PathLike, str]) -> dict:
    """The manifest of an entry (or failure record) folder."""
    from .cache import MANIFEST, read_json

    return read_json(Path(entry_dir) / MANIFEST)
