"""From collected run data to the report's records: method descriptions, the result tables
(by method, by scene x method, by object), the quoted paper numbers beside them, and the
data of the plots. Numbers are averaged exactly as the summary stage does
(:func:`cobgs.evaluate.protocols.aggregate`: over objects within a scene, then over scenes).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

from . import paper
from .collect import Result, RunData, TaskRecord
from .fmt import finite

from cobgs.configs import NOSPLIT_SWITCHES, Files
from cobgs.refine.methods import REGISTRY
from cobgs.data.spec import DatasetSpec
from cobgs.evaluate.protocols import ORACLE_METHOD

KIND_LABELS = {name: m.label for name, m in REGISTRY.items()}  # (cobgs.refine.methods)
METRICS = ("iou", "acc", "biou", "iou_released", "biou_released", "iou_occlusion", "biou_occlusion", "psnr",
           "psnr_before_raem", "psnr_vanilla", "psnr_delta", "psnr_delta_before_raem", "num_gaussians",
           "num_gaussians_vanilla", "object_gaussians", "refine_s", "splits", "pruned", "dropped")
# The params section of the refine stage each method kind reads.
_SECTIONS = {name: m.sections for name, m in REGISTRY.items()}  # the params sections it reads
_EXTRA_STAGES = {name: m.extra_stage for name, m in REGISTRY.items() if m.extra_stage}

LogHref = Callable[[Optional[TaskRecord]], Optional[str]]


@dataclass
class MethodInfo:
    """A method axis value as the report names it.

    Attributes:
        name: the axis value.
        kind: the refine stage's ``method`` param (cobgs, nosplit, sa3d, flashsplat).
        options: params that differ from the refine stage's defaults (``bgtr=false``).
        role: "reference" (the COB-GS run the others are compared with), "variant"
            (another COB-GS configuration: ablation rows, δ sweeps) or "peer".
        paper: the paper's method it is (:func:`reports.paper.paper_method`), or None.
    """

    name: str
    kind: str = ""
    options: list[str] = field(default_factory=list)
    role: str = "peer"
    paper: Optional[tuple] = None
    raem: Optional[str] = None  # COB-GS's RAEM variant ("released", "paper", "off")
    # (BAGS, BGTR, RAEM on, object check) of a Table 5-style row (:func:`reports.paper.cobgs_switches`)
    switches: Optional[tuple] = None
    # a stage the method adds to COB-GS's ("NG-GS": cobgs.refine.methods.RefineMethod.extra_stage);
    # its switches are then those of the COB-GS it runs, and it is no faithful COB-GS row
    stage: str = ""

    @property
    def kind_label(self) -> str:
        return KIND_LABELS.get(self.kind, self.kind or "?")

    @property
    def config(self) -> str:
        return ", ".join(self.options) if self.options else "defaults"


def _flat(d, prefix: str = "") -> dict:
    out = {}
    for k, v in (d or {}).items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flat(v, key + "."))
        else:
            out[key] = v
    return out


def _value_text(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    return "none" if v is None else str(v)


def refine_defaults(workflow) -> dict:
    """The refine stage's default params as JSON (what an option differs from)."""
    from pipeline.params import to_json

    stage = workflow.graph.producer.get("refined")
    if stage is None:
        return {}
    return to_json(workflow.stages[stage].params())


# The no-split row forces COB-GS's switches off whatever the params say (cobgs.configs.NOSPLIT_SWITCHES)
_FORCED = {"nosplit": tuple(f"cobgs.{k}" for k in NOSPLIT_SWITCHES)}


def options_of(kind: str, params: Optional[dict], defaults: dict) -> list[str]:
    if not params:
        return []
    sections = _SECTIONS.get(kind, ())
    got, base = _flat(params), _flat(defaults)
    keep = [k for k in got if k not in ("method",) + _FORCED.get(kind, ())
            and (k.split(".")[0] in sections or "." not in k)]
    return [f"{k.split('.', 1)[-1]}={_value_text(got[k])}" for k in keep if got[k] != base.get(k)]


def method_infos(data: RunData) -> dict[str, MethodInfo]:
    defaults = refine_defaults(data.workflow)
    infos = {m: MethodInfo(m) for m in data.methods}
    seen: dict[str, set] = {}
    for r in data.results:
        info = infos.setdefault(r.method, MethodInfo(r.method))
        if r.refine_params is None:
            continue
        opts = options_of(r.method_kind, r.refine_params, defaults)
        if r.method not in seen:
            info.kind, info.options = r.method_kind, opts
            info.paper = paper.paper_method(r.method_kind, r.refine_params)
            info.stage = _EXTRA_STAGES.get(r.method_kind, "")
            base = "cobgs" if info.stage else r.method_kind  # the COB-GS a stage is added to
            info.switches = ((False, False, False, "off") if r.method_kind == "nosplit"
                             else paper.cobgs_switches(base, r.refine_params))
            if base == "cobgs":
                info.raem = str(((r.refine_params.get("cobgs") or {}).get("raem")
                                 or (defaults.get("cobgs") or {}).get("raem") or "released"))
        seen.setdefault(r.method, set()).add(tuple(sorted(opts)))  # the same options in any order
    for m, variants in seen.items():
        if len(variants) > 1:  # per-scene overrides: say so rather than pick one
            infos[m].options = infos[m].options + ["(varies by scene)"]
            infos[m].paper = infos[m].switches = None
    if ORACLE_METHOD in infos:
        picks = sorted({str((r.row or {}).get("oracle_choice")) for r in data.results if r.method == ORACLE_METHOD})
        infos[ORACLE_METHOD] = MethodInfo(ORACLE_METHOD, kind="flashsplat", options=[
            "best background bias per scene, chosen on the held-out GT (an oracle in its favour; "
            f"picked: {', '.join(picks)})"])
    ref = reference_method(infos)
    for m, info in infos.items():
        info.role = "reference" if m == ref else ("variant" if info.kind in ("cobgs", "nosplit") else "peer")
    return infos


def reference_method(infos: dict[str, MethodInfo]) -> Optional[str]:
    """The COB-GS item with default options, else the first COB-GS item, else the first."""
    for pick in (lambda i: i.kind == "cobgs" and not i.options, lambda i: i.kind == "cobgs", lambda i: True):
        for m, info in infos.items():
            if info.kind and pick(info):
                return m
    return next(iter(infos), None)


# -- result records ----------------------------------------------------------------------
def _refine_task(r: Result):
    t = r.tasks.get("refine")
    if t is None:
        prod = [s for s, tt in r.tasks.items() if tt.manifest and "refined" in (tt.manifest.get("outputs") or {})]
        t = r.tasks.get(prod[0]) if prod else None
    return t if t is not None and t.state == "done" else None


def _peak_rss(r: Result) -> Optional[float]:
    t = _refine_task(r)
    return finite((t.manifest or {}).get("peak_rss_bytes")) if t is not None else None


def _peak_gpu(r: Result) -> Optional[float]:
    """Peak GPU memory of the refine task (PyTorch's allocator; None for CPU runs)."""
    t = _refine_task(r)
    return finite((t.manifest or {}).get("gpu_peak_bytes")) if t is not None else None


def _max_or_none(values) -> Optional[float]:
    vals = [v for v in values if v is not None]
    return max(vals) if vals else None


def _status(results: list[Result], log_href: LogHref) -> tuple[str, list[str], Optional[str], str]:
    """(text, classes, href, title) of the status of a group of results."""
    ok = [r for r in results if r.ok]
    if len(ok) == len(results):
        return "complete", ["ok"], None, ""
    bad = next(r for r in results if not r.ok)
    p = bad.problem
    if p is None:
        return "no metrics", ["missing"], None, ""
    what = f"{p.state}: {p.stage}"
    text = what if not ok else f"{len(ok)} of {len(results)} done; {what}"
    cls = ["failed"] if p.state in ("failed", "corrupt") else ["missing"]
    task = bad.tasks.get(p.stage)
    return text, cls, log_href(task) if p.state == "failed" else None, f"{p.stage}[{p.item_id}]: {p.message}"


def _aggregate(rows: list[dict], by: tuple[str, ...]) -> list[dict]:
    from cobgs.evaluate.protocols import aggregate

    return aggregate(rows, METRICS, by=by, within="scene", over="object")


def _rows(results: list[Result]) -> list[dict]:
    out = []
    for r in results:
        if r.ok:
            row = dict(r.row)
            row.update(scene=r.scene, method=r.method, object=r.object, refine_s=_refine_s(r))
            out.append(row)
    return out


def _refine_note(r: Result) -> dict:
    """What the refine task recorded in its manifest (timings, memory: not in artifacts)."""
    t = _refine_task(r)
    return ((t.manifest or {}).get("extra") or {}) if t is not None else {}


def _refine_s(r: Result) -> Optional[float]:
    return finite(_refine_note(r).get("refine_s"))


def object_records(data: RunData, infos: dict, log_href: LogHref) -> list[dict]:
    recs = []
    for r in data.results:
        row = r.row or {}
        status, cls, href, title = _status([r], log_href)
        amb = finite(row.get("ambiguous_final"))
        recs.append({
            "scene": r.scene, "method": r.method, "object": r.object, "status": status,
            "iou": row.get("iou"), "acc": row.get("acc"), "biou": row.get("biou"), "views": row.get("views"),
            "biou_released": row.get("biou_released"), "biou_occlusion": row.get("biou_occlusion"),
            "iou_released": row.get("iou_released"), "iou_occlusion": row.get("iou_occlusion"),
            "mask_route": row.get("mask_route"),
            "psnr": row.get("psnr"), "psnr_delta": row.get("psnr_delta"), "num_gaussians": row.get("num_gaussians"),
            "psnr_before_raem": row.get("psnr_before_raem"),
            "psnr_delta_before_raem": row.get("psnr_delta_before_raem"),
            "splits": row.get("splits"), "pruned": row.get("pruned"), "dropped": row.get("dropped"),
            "ambiguous_final": amb if amb is not None and amb >= 0 else None,
            "refine_s": _refine_s(r) if r.ok else None, "peak_rss": _peak_rss(r) if r.ok else None,
            "peak_gpu": _peak_gpu(r) if r.ok else None,
            "_class": {"status": cls, "method": _ref_class(infos, r.method)},
            "_href": {"status": href} if href else {},
            "_title": {"status": title, "method": infos[r.method].config if r.method in infos else "",
                       "views": _skipped_title(r)},
            "_row_class": [] if r.ok else ["incomplete"], "_nobest": not r.ok,
        })
    return recs


def _skipped_title(r: Result) -> str:
    if not r.skipped:
        return ""
    items = list(r.skipped.items())
    text = "; ".join(f"{v}: {why}" for v, why in items[:8])
    return f"skipped {len(items)} view(s): {text}" + (" ..." if len(items) > 8 else "")


def _scene_tasks(data: RunData, scene: str) -> list[str]:
    """Every NVOS task a workflow scene holds (two for a shared horns scene)."""
    ds = data.scenes.get(scene)
    spec = DatasetSpec(ds.dataset or {}) if ds is not None else DatasetSpec()
    if spec.nvos_tasks:
        return sorted(spec.nvos_tasks)
    return [_scene_task(data, scene)]


def _scene_task(data: RunData, scene: str) -> str:
    """The NVOS task / LERF-mask scene a workflow scene stands for (paper lookups; a scene
    holding several NVOS tasks stands for its first: they share the scene's PSNR)."""
    ds = data.scenes.get(scene)
    spec = DatasetSpec(ds.dataset or {}) if ds is not None else DatasetSpec()
    if spec.protocol == "nvos":
        return str((spec.nvos or {}).get("task") or scene)
    if spec.protocol == "lerf_mask":
        src = spec.source or ""
        base = Path(src).name.lower() if src else ""
        return base if base in paper.LERF_SCENES else scene.lower()
    return scene


def _route(r: Result) -> str:
    return str((r.row or {}).get("mask_route") or "")


def _scene_route_key(results: list[Result]):
    """key(result) -> (scene, mask route), the route None where the scene uses one route
    only: exact- and noisy-mask objects of a scene are different experiments, never
    averaged or compared together."""
    routes: dict[str, set] = {}
    for r in results:
        if r.ok:
            routes.setdefault(r.scene, set()).add(_route(r))
    return lambda r: (r.scene, _route(r) if len(routes.get(r.scene, ())) > 1 else None)


def scene_method_records(data: RunData, infos: dict, log_href: LogHref) -> list[dict]:
    """Per scene x method, and per mask route where a scene mixes routes (exact and noisy
    masks are different experiments: their objects are never averaged together)."""
    key = _scene_route_key(data.results)
    groups: dict[tuple, list[Result]] = {}
    for r in data.results:
        scene, route = key(r)
        groups.setdefault((scene, r.method, route), []).append(r)
    recs = []
    for (scene, method, route), rs in groups.items():
        agg = _aggregate(_rows(rs), ("scene", "method"))
        rec = dict(agg[0]) if agg else {"scene": scene, "method": method}
        status, cls, href, title = _status(rs, log_href)
        info = infos.get(method, MethodInfo(method))
        rec.update(scene=scene, method=method, config=info.config, status=status, masks=route,
                   _group=f"{scene}/{route or ''}",
                   objects=sum(r.ok for r in rs), objects_total=len(rs), peak_rss=_max_or_none(_peak_rss(r) for r in rs if r.ok),
                   peak_gpu=_max_or_none(_peak_gpu(r) for r in rs if r.ok),
                   _class={"status": cls, "method": _ref_class(infos, method)}, _href={"status": href} if href else {},
                   _title={"status": title}, _sub={"method": _method_sub(info)},
                   _nobest=not all(r.ok for r in rs), _row_class=[f"role-{info.role}"])
        rec["_text"] = {"objects": f"{rec['objects']} of {len(rs)}" if rec["objects"] < len(rs) else str(len(rs))}
        _paper_scene(data, rec, info)
        recs.append(rec)
    return recs


def _paper_scene(data: RunData, rec: dict, info: MethodInfo) -> None:
    protocol = data.scenes[rec["scene"]].protocol if rec["scene"] in data.scenes else ""
    task = _scene_task(data, rec["scene"])
    if protocol == "nvos":
        q = paper.nvos_psnr_quote(task, info.paper)
        if q is not None:
            rec["paper_psnr"] = q.values["psnr"]
            rec["_text"]["paper_psnr"] = f"{q.values['psnr']:.2f} ({q.values['psnr_vanilla']:.2f})"
            rec["_title"]["paper_psnr"] = (f"quoted, {q.source}: {q.label} on {task}; in brackets the "
                                           "paper's vanilla scene")
    elif protocol == "lerf_mask":
        q = paper.lerf_quote(task, info.paper)
        if q is not None:
            rec["paper_iou"], rec["paper_biou"] = q.values["iou"] / 100.0, q.values["biou"] / 100.0
            rec["_title"]["paper_iou"] = rec["_title"]["paper_biou"] = f"quoted, {q.source}: {q.label} on {task}"


def _ref_class(infos: dict, method: str) -> list[str]:
    return ["ref"] if method in infos and infos[method].role == "reference" else []


def _method_sub(info: MethodInfo) -> str:
    return info.kind_label + ("" if not info.options else " · " + info.config)


def method_records(data: RunData, infos: dict, log_href: LogHref) -> tuple[list[dict], list[str]]:
    """Per method over every scene; also the notes the paper columns need."""
    notes: list[str] = []
    scenes = list(data.scenes)
    covered = {(r.scene, r.object) for r in data.results}  # a method run on part of it (`only`) is not ranked
    recs = []
    for method in data.methods:
        rs = [r for r in data.results if r.method == method]
        if not rs:
            continue
        agg = _aggregate(_rows(rs), ("method",))
        rec = dict(agg[0]) if agg else {"method": method}
        status, cls, href, title = _status(rs, log_href)
        info = infos.get(method, MethodInfo(method))
        done_scenes = sorted({r.scene for r in rs if r.ok}, key=scenes.index)
        rec.update(method=method, kind=info.kind_label, config=info.config, status=status,
                   scenes=len(done_scenes), objects_total=len(rs), peak_rss=_max_or_none(_peak_rss(r) for r in rs if r.ok),
                   peak_gpu=_max_or_none(_peak_gpu(r) for r in rs if r.ok),
                   objects=sum(r.ok for r in rs), _class={"status": cls, "method": _ref_class(infos, method)},
                   _href={"status": href} if href else {},
                   _title={"status": title}, _sub={"method": _method_sub(info)},
                   # a mean over fewer scenes or objects is not comparable: never "best"
                   _nobest=not all(r.ok for r in rs) or {(r.scene, r.object) for r in rs} != covered,
                   _row_class=[f"role-{info.role}"])
        in_scenes = len({r.scene for r in rs})  # a method limited by `only` runs in fewer
        rec["_text"] = {"scenes": f"{len(done_scenes)} of {in_scenes}" if len(done_scenes) < in_scenes
                        else str(in_scenes),
                        "objects": f"{rec['objects']} of {len(rs)}" if rec["objects"] < len(rs) else str(len(rs))}
        protocols = {data.scenes[s].protocol for s in done_scenes}
        q = paper.nvos_quote(info.paper) if protocols == {"nvos"} else None
        if q is not None:
            rec["paper_iou"], rec["paper_acc"] = q.values["iou"] / 100.0, q.values["acc"] / 100.0
            tasks = sorted({t for s in done_scenes for t in _scene_tasks(data, s)})
            src = f"quoted, {q.source}: {q.label}"
            if len(tasks) < len(paper.NVOS_TASKS):
                src += f"; this run covers {len(tasks)} of the {len(paper.NVOS_TASKS)} tasks, not comparable as a mean"
                rec["_class"]["paper_iou"] = rec["_class"]["paper_acc"] = ["partial"]
            rec["_title"]["paper_iou"] = rec["_title"]["paper_acc"] = src
        recs.append(rec)
    if any("paper_iou" in r for r in recs):
        notes.append("Columns marked † are quoted from the paper (authors' runs on an RTX 3090), "
                     "not measured here; they never take part in best-value marking.")
    return recs, notes


def scene_records(data: RunData) -> list[dict]:
    recs = []
    for name, sc in data.scenes.items():
        t, spec = sc.train or {}, DatasetSpec(sc.dataset or {})
        ev = t.get("eval") or {}
        recs.append({"scene": name, "kind": spec.get("kind"), "protocol": spec.get("protocol"),
                     "scene_type": spec.get("scene_type"),
                     "views": len(spec.views) or None, "test_views": len(spec.test_views)
                     if spec else None, "objects": ", ".join(spec.objects),
                     "iterations": t.get("iterations"), "num_gaussians": t.get("num_gaussians"),
                     "train_s": _train_s(sc, t), "psnr": ev.get("psnr"), "ssim": ev.get("ssim"),
                     "status": sc.train_task.state if sc.train_task else "not in workflow",
                     "notes": "; ".join([*spec.notes, *_recipe_note(t), *_init_note(t)])})
    return recs


def _recipe_note(t: dict) -> list[str]:
    """The training recipe a trained scene used (``train.json``'s config; a 3DGS run leaves the
    field out at its default, "3dgs"). Nothing for a scene trained elsewhere."""
    cfg = t.get("config")
    if not isinstance(cfg, dict) or t.get("imported"):
        return []
    recipe = cfg.get("recipe", "3dgs")
    if recipe == "3dgs":
        return [f"training recipe: 3dgs (the paper's schedule, {t.get('iterations') or cfg.get('iterations')} iterations)"]
    parts = [f"{t.get('iterations') or cfg.get('iterations')} iterations"]
    if cfg.get("resolution_schedule"):
        parts.append("resolution schedule")
    if cfg.get("gaussian_budget") or cfg.get("gaussian_budget_per_pixel") or cfg.get("gaussian_budget_multiplier"):
        rule = [f"{cfg[k]}{unit}" for k, unit in (("gaussian_budget_per_pixel", " per pixel"),
                                                  ("gaussian_budget_multiplier", " x the initial points")) if cfg.get(k)]
        count = cfg.get("gaussian_budget") or t.get("gaussian_budget")
        text = f"Gaussian budget {count:,}" if isinstance(count, int) else "Gaussian budget"
        if rule and not cfg.get("gaussian_budget"):
            text += f" ({' or '.join(rule)}, the larger)" if len(rule) > 1 else f" ({rule[0]})"
        if cfg.get("budget_threshold_gate"):
            text += " as a ceiling"
        parts.append(text)
    if cfg.get("sparse_adam"):
        parts.append("visible-only Adam")
    if cfg.get("fast_kernels"):
        parts.append("fast CPU kernels")
    return [f"training recipe: {recipe} ({', '.join(parts)})"]


def _init_note(t: dict) -> list[str]:
    """A note when training started from a random box instead of SfM / triangulated points."""
    init = t.get("initial_points")
    if isinstance(init, str) and init.startswith("random box"):
        return [f"training started from a {init} of points, not from SfM or triangulated points "
                "(the 3DGS recipe for NeRF-synthetic; on a real capture expect a weaker baseline: set "
                "sfm.mode or keep sfm.triangulate on)"]
    return []


def _train_s(sc, t: dict) -> Optional[float]:
    """Training wall time, from the train task's manifest (older entries: train.json)."""
    m = (sc.train_task.manifest or {}) if sc.train_task is not None else {}
    return finite((m.get("extra") or {}).get("train_s", t.get("wall_s")))


# -- plot data ---------------------------------------------------------------------------
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


def task_records(data: RunData, log_href: LogHref) -> list[dict]:
    recs = []
    for i, t in enumerate(data.tasks):
        m = t.manifest or {}
        href = log_href(t) if t.state in ("done", "failed") else None
        recs.append({"order": i, "stage": t.stage, "item": t.item_id, "state": t.state, "key": t.key or "",
                     "version": m.get("version"), "wall_s": m.get("wall_s"), "cpu_s": m.get("cpu_s"),
                     "peak_rss": m.get("peak_rss_bytes"), "peak_gpu": m.get("gpu_peak_bytes"),
                     "host": (f"{m.get('host')} (Ray node {m['node'][:8]})" if m.get("node")
                              else m.get("host")), "device": m.get("device"),
                     "started": m.get("started"), "log": "log" if href else "",
                     "_href": {"log": href} if href else {}, "_class": {"state": [t.state]},
                     "_title": {"key": t.key or "", "state": t.error}})
    return recs


def difference_records(data: RunData, infos: dict, ref: Optional[str]) -> tuple[list[dict], list[str]]:
    """Per scene (and mask route, where a scene mixes them): the reference method's headline
    mBIoU minus each peer's, the no-split row's and, where the reference is the checked
    variant, its faithful COB-GS twin's (:func:`faithful_twins`), in points, with a 95 % interval from
    resampling the held-out views of each object (:func:`cobgs.evaluate.protocols.bootstrap_mean_diff`).

    Returns:
        (records with one "d:<method>" cell per compared method, the compared methods).
    """
    from cobgs.evaluate.protocols import bootstrap_mean_diff

    if ref is None:
        return [], []
    twins = faithful_twins(infos, ref)
    others = [m for m in data.methods if m != ref and m in infos
              and (infos[m].role == "peer" or infos[m].kind == "nosplit" or m in twins)]
    key = _scene_route_key(data.results)
    groups: dict[tuple, dict] = {}
    for r in data.results:
        if r.ok:
            groups.setdefault(key(r), {}).setdefault(r.method, {})[r.object] = r
    recs, used = [], []
    for (scene, route), by_method in groups.items():
        mine = by_method.get(ref, {})
        rec: dict = {"scene": scene, "masks": route, "_text": {}, "_title": {}}
        for m in others:
            theirs = by_method.get(m, {})
            pairs = {}
            for obj, a in mine.items():
                b = theirs.get(obj)
                if b is None:
                    continue
                pairs[obj] = [(va["biou"], b.per_view[v]["biou"]) for v, va in a.per_view.items()
                              if v in b.per_view and va.get("biou") is not None
                              and b.per_view[v].get("biou") is not None]
            d = bootstrap_mean_diff(pairs)
            if d is None:
                continue
            if m not in used:
                used.append(m)
            rec[f"d:{m}"], rec[f"lo:{m}"], rec[f"hi:{m}"] = d["diff"], d["lo"], d["hi"]
            rec["_text"][f"d:{m}"] = f"{d['diff']:+.2f} [{d['lo']:+.2f}, {d['hi']:+.2f}]"
            below = d["hi"] < 0
            above = d["lo"] > 0
            rec.setdefault("_class", {})[f"d:{m}"] = ["worse"] if below else (["better"] if above else [])
            rec["_title"][f"d:{m}"] = (f"{ref} minus {m}: {d['objects']} objects, {d['views']} views; "
                                       + ("significantly below" if below else "significantly above" if above
                                          else "interval includes 0"))
        recs.append(rec)
    return recs, used


# -- paper Tables 5 and 4 at benchmark scale ---------------------------------------------
def _switch_order(sw: tuple) -> tuple:
    """none, BAGS, BAGS + BGTR, all three (the paper's rows); other combinations by count."""
    return (sum(sw), tuple(not x for x in sw))


_RAEM_ORDER = {"off": 0, "released": 1, "paper": 2}


def _switches(info: Optional[MethodInfo]) -> Optional[tuple]:
    """(BAGS, BGTR, RAEM) of a Table 5 row: COB-GS and its switch ablations, no-split = none
    (with or without the object-render check: :func:`_check`)."""
    if info is None or info.switches is None:
        return None
    return tuple(info.switches[:3])


def _check(info: Optional[MethodInfo]) -> str:
    """The object-render check of a Table 5-style row ("off" / "visible")."""
    return str(info.switches[3]) if info is not None and info.switches is not None else "off"


def faithful_twins(infos: dict, ref: Optional[str]) -> list[str]:
    """The faithful COB-GS rows the reference is the checked variant of: all three switches
    on, the same RAEM, object check off (docs/method.md §7: our variant beside the faithful)."""
    mine = infos.get(ref) if ref else None
    if mine is None or mine.switches is None or _check(mine) == "off":
        return []
    return [m for m, i in infos.items() if m != ref and i.switches is not None and _check(i) == "off"
            and not i.stage and tuple(i.switches[:3]) == tuple(mine.switches[:3]) and i.raem == mine.raem]


def ablation_records(by_scene: list[dict], infos: dict) -> list[dict]:
    """Paper Table 5 per scene (and mask route): the rows that switch BAGS, BGTR and RAEM on
    and off (the no-split row = none of them), in the paper's order, each RAEM variant apart.

    Rows are the per scene x method records (:func:`scene_method_records`), so the numbers
    are the same as in the results table; only the selection, order and switch columns are
    new. Best values are marked within a scene and route.
    """
    order = {g: i for i, g in enumerate(dict.fromkeys(r["_group"] for r in by_scene))}
    out = []
    for rec in by_scene:
        info = infos.get(rec["method"])
        sw = _switches(info)
        if sw is None:
            continue
        raem = "off" if not sw[2] else (info.raem or "released")
        check = _check(info)
        row = dict(rec)
        row.update(bags="✓" if sw[0] else "", bgtr="✓" if sw[1] else "", raem=raem,
                   check="" if check == "off" else check, stage=info.stage,
                   _sort=(order[rec["_group"]], _switch_order(sw), _RAEM_ORDER.get(raem, 3), check != "off",
                          info.stage, rec["method"]))
        row["_text"] = dict(rec.get("_text") or {})
        out.append(row)
    out.sort(key=lambda r: r["_sort"])
    return out if len({r["_sort"][1] for r in out}) >= 2 else []


def psnr_records(by_scene: list[dict], infos: dict, ref: Optional[str]) -> list[dict]:
    """Paper Table 4 per scene (and mask route): held-out PSNR of the vanilla scene, after the
    mask stages alone (BAGS, no BGTR: "M.O"), after mask + texture stages before RAEM (the
    reference's scene before its final pruning: "M.O+T.O", the paper's measurement), and after
    each RAEM variant. Means over the scene's objects, like every per-scene number.

    The paper's "texture only" column (texture stages without splitting) has no row in
    our ablations: left out rather than approximated.
    """
    groups: dict[str, list[dict]] = {}
    for rec in by_scene:
        groups.setdefault(rec["_group"], []).append(rec)
    out = []
    for g, recs in groups.items():
        by_m = {r["method"]: r for r in recs}
        row: dict = {"scene": recs[0]["scene"], "masks": recs[0].get("masks"), "_title": {}, "_text": {}}
        vanilla = next((finite(r.get("psnr_vanilla")) for r in recs if finite(r.get("psnr_vanilla")) is not None),
                       None)
        row["vanilla"] = vanilla
        for r in recs:
            sw = _switches(infos.get(r["method"]))
            if sw == (True, False, False) and "mask_only" not in row:
                row["mask_only"], row["_title"]["mask_only"] = finite(r.get("psnr")), f"{r['method']}"
        mine = by_m.get(ref) if ref else None
        if mine is not None:
            row["joint"] = finite(mine.get("psnr_before_raem"))
            row["_title"]["joint"] = f"{ref}, its scene before RAEM"
        for r in recs:
            info = infos.get(r["method"])
            if _switches(info) == (True, True, True) and info.raem and not info.stage:
                key = f"raem_{info.raem}"
                if key not in row or r["method"] == ref:
                    row[key], row["_title"][key] = finite(r.get("psnr")), r["method"]
        if vanilla is None or all(row.get(k) is None for k in ("mask_only", "joint")):
            continue
        for k in ("mask_only", "joint", "raem_released", "raem_paper"):
            if row.get(k) is not None:
                row[f"d_{k}"] = row[k] - vanilla
        if row.get("joint") is not None:
            ok = row["joint"] >= vanilla - 0.1
            row["target"] = "met" if ok else "not met"
            row["_class"] = {"target": ["ok" if ok else "failed"]}
            row["_title"]["target"] = f"before-RAEM PSNR {row['joint'] - vanilla:+.3f} dB vs vanilla (bar −0.1 dB)"
        out.append(row)
    return out
