"""The report's result records: by object, by scene x method, by method (with the quoted
paper numbers beside them), by scene, the tasks, and the differences against the reference.
Numbers are averaged exactly as the summary stage does (:func:`cobgs.evaluate.protocols.aggregate`:
over objects within a scene, then over scenes)."""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Optional

from cobgs.data.spec import DatasetSpec
from cobgs.evaluate.protocols import METRICS, aggregate

from . import paper
from .collect import Result, RunData, TaskRecord
from .fmt import finite

from .ablation import faithful_twins
from .methods import MethodInfo

LogHref = Callable[[Optional[TaskRecord]], Optional[str]]


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


#: What the report averages: the result metrics (:data:`cobgs.evaluate.protocols.METRICS`, as the
#: summary stage) and the refinement's counts and times.
RECORD_FIELDS = (*METRICS, "num_gaussians_vanilla", "refine_s", "splits", "pruned", "dropped")


def _aggregate(rows: list[dict], by: tuple[str, ...]) -> list[dict]:
    return aggregate(rows, RECORD_FIELDS, by=by, within="scene", over="object")


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


