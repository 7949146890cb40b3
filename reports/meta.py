"""Run metadata: what ran, where, when, with which versions and params (from the manifests),
plus the environment the report itself was built in (labelled as such). Manifests record
the versions of the distributions each task imported; the report lists them per run."""

from __future__ import annotations

import json
import os
import platform
import socket
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Optional

from .collect import RunData
from .fmt import finite

DEPENDENCIES = ("cobgs", "torch", "numpy", "pycolmap", "onnxruntime", "onnx", "opencv-contrib-python-headless",
                "scikit-image", "pillow", "plyfile", "pandas", "jinja2", "matplotlib", "tqdm", "ray")


def package_versions(names=DEPENDENCIES) -> list[tuple[str, str]]:
    from importlib import metadata

    out = []
    for n in names:
        try:
            out.append((n, metadata.version(n)))
        except metadata.PackageNotFoundError:
            out.append((n, "not installed"))
    return out


def _distinct(values) -> str:
    c = Counter(v for v in values if v not in (None, ""))
    if not c:
        return ""
    return ", ".join(f"{v} ({n} tasks)" if len(c) > 1 else str(v) for v, n in c.most_common())


def run_metadata(data: RunData, sets: list[str]) -> dict:
    wf = data.workflow
    mans = [t.manifest for t in data.tasks if t.manifest and t.state in ("done", "failed")]
    started = [finite(m.get("started")) for m in mans]
    finished = [finite(m.get("finished")) for m in mans]
    started = [s for s in started if s is not None]
    finished = [f for f in finished if f is not None]
    try:
        text = Path(wf.path).read_text(encoding="utf-8")
    except OSError as exc:
        text = f"(could not read {wf.path}: {exc})"
    return {
        "workflow": {"name": wf.name, "description": wf.description, "path": os.fspath(wf.path),
                     "text": text, "targets": list(wf.targets), "device": wf.settings.device, "sets": list(sets),
                     "axes": {a: _axis_values(wf, a) for a in wf.axes.order}},
        "cache_dir": os.fspath(data.cache_dir.resolve()),
        "started": min(started) if started else None,
        "finished": max(finished) if finished else None,
        "wall_s": sum(finite(m.get("wall_s")) or 0.0 for m in mans),
        "cpu_s": sum((finite(m.get("cpu_s")) or 0.0) + (finite(m.get("cpu_children_s")) or 0.0) for m in mans),
        "hosts": _distinct(m.get("host") for m in mans),
        "devices": _distinct(m.get("device") for m in mans if m.get("uses_device")),
        "executors": _distinct(m.get("executor") for m in mans),
        "python": _distinct((m.get("python") or "").split()[0] if m.get("python") else None for m in mans),
        "package_versions": _distinct(m.get("package_version") for m in mans),
        "dependencies": run_dependencies(mans),
        "counts": data.counts(),
    }


def run_dependencies(mans: list[dict]) -> list[tuple[str, str]]:
    """Per distribution the stages imported, the versions recorded in the manifests (older
    entries, written before manifests recorded them, contribute nothing)."""
    seen: dict[str, list[str]] = {}
    for m in mans:
        deps = m.get("dependencies")
        if isinstance(deps, dict):
            for name, version in deps.items():
                seen.setdefault(str(name), []).append(str(version))
    return [(name, _distinct(versions)) for name, versions in sorted(seen.items(), key=lambda kv: kv[0].lower())]


def _axis_values(wf, axis: str) -> list[str]:
    ax = wf.axes[axis]
    if ax.parent is None:
        return ax.names()
    return [f"{p}/{v}" for p in wf.axes[ax.parent].names() for v in ax.names(p)]


def stage_records(data: RunData) -> list[dict]:
    """Per stage: current version, versions found in the cache, level, params sets."""
    wf = data.workflow
    recs = []
    for name in wf.graph.order:
        st = wf.stages[name]
        tasks = [t for t in data.tasks if t.stage == name]
        versions = sorted({t.manifest.get("version") for t in tasks if t.manifest and t.state == "done"} - {None})
        params: dict[str, list[str]] = {}
        for t in tasks:
            js = json.dumps(wf.params_for(name, t.item).json, indent=1, sort_keys=True)
            params.setdefault(js, []).append(t.item_id)
        states = Counter(t.state for t in tasks)
        recs.append({"stage": name, "version": st.version, "cached_versions": versions,
                     "level": " x ".join(wf.levels[name]) or "workflow", "description": st.description,
                     "tasks": len(tasks), "states": ", ".join(f"{n} {s}" for s, n in sorted(states.items())),
                     "params": [{"json": js, "items": items} for js, items in params.items()]})
    return recs


def report_environment() -> dict:
    return {"generated": time.time(), "host": socket.gethostname(), "python": sys.version.split()[0],
            "platform": platform.platform(), "packages": package_versions()}


def first_time(values) -> Optional[float]:
    vals = [v for v in (finite(x) for x in values) if v is not None]
    return min(vals) if vals else None
