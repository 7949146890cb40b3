"""The data the report's plots draw: time per stage, the δ sweep, the score curves, the
refinement stages of the reference."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

from cobgs.configs import Files

from .collect import RunData
from .fmt import finite

from .methods import MethodInfo
from .records import _refine_note


def stage_time_bars(data: RunData) -> tuple[list[tuple[str, dict]], list[str]]:
    """[(label, {stage: wall s})]: one bar for the stages shared by every method, one per
    method (its own tasks), and the order of the stages."""
    wf = data.workflow
    shared: dict = {}
    per: dict = {m: {} for m in data.methods}
    for t in data.tasks:
        if t.state != "done" or not t.manifest:
            continue
        w = finite(t.manifest.get("wall_s")) or 0.0
        m = t.values.get("method")
        target = per.setdefault(m, {}) if m is not None else shared
        target[t.stage] = target.get(t.stage, 0.0) + w
    bars = [("shared by all methods", shared)] if shared else []
    bars += [(m, per[m]) for m in data.methods if per.get(m)]
    return bars, list(wf.graph.order)


FIXED_DELTA = 0.5  # the paper's forward-facing δ: one yardstick for every run of a sweep


def delta_groups(data: RunData, infos: dict) -> list[tuple[str, list[tuple]]]:
    """COB-GS results that differ only in δ, per scene x object: the paper's Fig. 7.

    Returns:
        [(label, [(δ, ambiguous under the run's own δ, total Gaussians, ambiguous under
        :data:`FIXED_DELTA` at the last mask stage or None)])]; empty without a sweep. The
        own-δ count grows with δ by construction (a higher bar flags more), so the fixed
        yardstick is what shows whether more splitting left fewer ambiguous Gaussians.
    """
    import numpy as np

    groups: dict[tuple, dict] = {}
    for r in data.results:
        if not r.ok or r.refine is None or infos.get(r.method, MethodInfo(r.method)).kind != "cobgs":
            continue
        d = finite(r.refine.get("delta"))
        if d is None:
            continue
        opts = tuple(o for o in infos[r.method].options if not o.startswith("delta="))
        amb = finite(r.refine.get("ambiguous_final"))
        if amb is None or amb < 0:
            masks = [s for s in r.refine.get("stages") or [] if s.get("kind") == "mask" and s.get("ambiguous", -1) >= 0]
            amb = float(masks[-1]["ambiguous"]) if masks else None
        total = finite(r.refine.get("num_gaussians_end"))
        if amb is None or total is None:
            continue
        fixed = None
        f = Path(r.refine_dir) / Files.STAGE_SCORES if r.refine_dir else None
        if f is not None and f.is_file():
            with np.load(f) as z:
                last = max(z.files, key=lambda k: int(k.rsplit("_", 1)[-1]), default=None)
                if last is not None and z[last].size:
                    fixed = float(np.count_nonzero(z[last] < FIXED_DELTA))
        groups.setdefault((r.scene, r.object, opts), {})[d] = (d, amb, total, fixed)
    out = []
    for (scene, obj, opts), pts in groups.items():
        if len(pts) >= 2:
            label = f"{scene} / {obj}" + (f" ({', '.join(opts)})" if opts else "")
            out.append((label, list(pts.values())))
    return out


def score_panels(data: RunData, method: Optional[str], limit: int = 4):
    """Stage-mean scores of every mask stage of ``method``'s results (stage_scores.npz)."""
    import numpy as np

    panels, skipped = [], 0
    for r in data.results:
        if r.method != method or not r.ok or r.refine_dir is None:
            continue
        f = Path(r.refine_dir) / Files.STAGE_SCORES
        if not f.is_file():
            continue
        if len(panels) >= limit:
            skipped += 1
            continue
        with np.load(f) as z:
            names = sorted(z.files, key=lambda k: int(k.split("_")[-1]) if k.split("_")[-1].isdigit() else 0)
            curves = [(f"mask stage {i + 1}", z[k]) for i, k in enumerate(names) if z[k].size]
        panels.append((f"{r.scene} / {r.object}", curves, finite((r.refine or {}).get("delta"))))
    return panels, skipped


def refine_stage_records(data: RunData, method: Optional[str]) -> list[dict]:
    """The per-stage statistics refine.json records for ``method`` (ambiguous, splits, ...)."""
    recs = []
    for r in data.results:
        if r.method != method or r.refine is None:
            continue
        walls = _refine_note(r).get("stage_wall_s") or []
        for i, s in enumerate(r.refine.get("stages") or []):
            amb = s.get("ambiguous", -1)
            large = s.get("ambiguous_large", -1)
            recs.append({"scene": r.scene, "object": r.object, "index": s.get("index"), "kind": s.get("kind"),
                         "iterations": s.get("iterations"), "g_start": s.get("gaussians_start"),
                         "g_end": s.get("gaussians_end"), "ambiguous": amb if amb is not None and amb >= 0 else None,
                         "ambiguous_large": large if large is not None and large >= 0 else None,
                         "split": s.get("split"), "pruned": s.get("pruned"), "loss": s.get("mean_loss"),
                         "wall_s": walls[i] if i < len(walls) else s.get("wall_s")})
    return recs


