"""Stage-by-stage refinement records (``tests/benchmarks/bm_refine_trajectory.py``) for the
report's refinement section.

The records are not in the cache: the trajectory script reruns a workflow row with hooks at
every stage and writes one JSON file per (scene, method, object). ``cobgs report
--trajectories DIR`` reads the files of DIR whose scene is one of the run's and draws, per
scene, the held-out IoU / boundary IoU after every mask and texture stage.

Each file is checked when it is read: a file that is not such a record stops the report with
its path and the field at fault, rather than drawing a wrong curve.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Iterable

from .errors import ReportError

STAGE_KINDS = ("mask", "texture", "check")
MAX_FILES = 500
MAX_BYTES = 8 << 20


def _number(path: Path, where: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ReportError(f"{path}: {where}: expected a finite number, got {value!r}")
    return float(value)


def _check(path: Path, rec) -> dict:
    if not isinstance(rec, dict):
        raise ReportError(f"{path}: expected a JSON object (a bm_refine_trajectory.py record), "
                          f"got {type(rec).__name__}")
    for key in ("scene", "method", "object"):
        if not isinstance(rec.get(key), str) or not rec[key]:
            raise ReportError(f"{path}: field {key!r}: expected a non-empty string, got {rec.get(key)!r}")
    start = rec.get("start")
    if not isinstance(start, dict):
        raise ReportError(f"{path}: field 'start': expected an object with iou / biou, got {start!r}")
    out = {"scene": rec["scene"], "method": rec["method"], "object": rec["object"], "path": path,
           "start": {k: _number(path, f"start.{k}", start.get(k)) for k in ("iou", "biou")}, "stages": []}
    stages = rec.get("stages")
    if not isinstance(stages, list) or not stages:
        raise ReportError(f"{path}: field 'stages': expected a non-empty list, got {stages!r:.80}")
    for i, st in enumerate(stages):
        if not isinstance(st, dict):
            raise ReportError(f"{path}: stages[{i}]: expected an object, got {st!r:.80}")
        kind = st.get("kind")
        if kind not in STAGE_KINDS:
            raise ReportError(f"{path}: stages[{i}].kind: expected one of {', '.join(STAGE_KINDS)}, got {kind!r}")
        row = {"kind": kind}
        for k in ("iou", "biou"):
            row[k] = _number(path, f"stages[{i}].{k}", st.get(k))
        for k in ("cf_iou", "cf_biou"):  # the closed-form labels' scores: optional
            if st.get(k) is not None:
                row[k] = _number(path, f"stages[{i}].{k}", st.get(k))
        out["stages"].append(row)
    return out


def load_trajectories(folder, scenes: Iterable[str]) -> list[dict]:
    """The records of ``folder`` (``*.json``) whose scene is in ``scenes``, sorted by scene,
    method and object; a folder that does not exist or an unreadable record is a ReportError."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ReportError(f"--trajectories {folder}: not a folder (expected the JSON files "
                          "tests/benchmarks/bm_refine_trajectory.py writes)")
    files = sorted(p for p in folder.glob("*.json") if p.is_file())
    if len(files) > MAX_FILES:
        raise ReportError(f"--trajectories {folder}: {len(files)} JSON files, at most {MAX_FILES} are read")
    wanted = set(scenes)
    out = []
    for p in files:
        if p.stat().st_size > MAX_BYTES:
            raise ReportError(f"{p}: {p.stat().st_size} bytes, larger than a trajectory record can be "
                              f"({MAX_BYTES} at most)")
        try:
            rec = json.loads(p.read_text(encoding="utf-8"))
        except (UnicodeDecodeError, ValueError, RecursionError) as exc:
            raise ReportError(f"{p}: not a JSON trajectory record: {exc}") from None
        rec = _check(p, rec)
        if rec["scene"] in wanted:
            out.append(rec)
    return sorted(out, key=lambda r: (r["scene"], r["method"], r["object"], str(r["path"])))


def by_scene(records: list[dict]) -> dict[str, list[dict]]:
    out: dict[str, list[dict]] = {}
    for r in records:
        out.setdefault(r["scene"], []).append(r)
    return out
