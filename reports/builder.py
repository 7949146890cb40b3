"""``build_report``: one self-contained report folder from a workflow's cache.

The folder (``index.html``, ``static/``, ``img/``, ``plots/``, ``logs/``, ``workflow.toml``,
``report.json``) uses relative links only and no network resource, so it opens from
``file://`` anywhere it is copied. It is written to a temporary sibling folder and renamed
into place once complete, so a crash never leaves a half-written report that looks whole;
an existing report at the destination is replaced, any other non-empty folder is refused.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path
from typing import Iterable, Optional

from . import fmt, results as R
from .collect import RunData, Task, collect
from .errors import ReportError
from .pictures import KIND_LABELS, MethodPictures, PictureSet, compose, read_mask, read_rgb, slug
from .tables import Column, build_table

MARKER = "report.json"
REPORT_FORMAT = "cobgs-report"
LOG_TAIL_BYTES = 1 << 20  # logs above this keep their last MiB (the end holds the traceback)
PACKAGE_DIR = Path(__file__).resolve().parent


def default_out_dir(workflow) -> Path:
    return Path("runs") / "reports" / workflow.name


def build_report(workflow_path: os.PathLike | str, out_dir: Optional[os.PathLike | str] = None,
                 cache_dir: Optional[os.PathLike | str] = None, sets: Iterable[str] = (),
                 registry=None, stream=None) -> Path:
    """Build the report of a workflow from its cache; returns the path of ``index.html``.

    Args:
        workflow_path: the workflow TOML file.
        out_dir: report folder (default ``runs/reports/<workflow name>``).
        cache_dir: cache folder (default: ``$COBGS_CACHE_DIR``, else ``runs/cache``).
        sets: ``--set`` overrides, as for ``cobgs run`` (they select the cache entries).
        registry: stage registry (default: the program's, :func:`stages.registry.load_registry`).
        stream: where to print progress lines (None: quiet).
    """
    from pipeline import load_workflow
    from pipeline.commands import default_cache_dir

    if registry is None:
        from stages.registry import load_registry

        registry = load_registry()
    sets = list(sets)
    wf = load_workflow(workflow_path, registry, sets=sets)
    cache = Path(default_cache_dir(os.fspath(cache_dir) if cache_dir else None))
    if not cache.is_dir():
        raise ReportError(f"workflow {wf.name!r}: cache folder {cache} does not exist; run "
                          f"`cobgs run {workflow_path}` first or pass --cache-dir")
    out = Path(out_dir) if out_dir else default_out_dir(wf)
    _check_destination(out)
    t0 = time.perf_counter()
    data = collect(wf, cache)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.tmp-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        _write(data, tmp, sets)
        _swap(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if stream is not None:
        print(f"report of {wf.name}: {out / 'index.html'} ({len(data.results)} results, "
              f"{len(data.failed)} failed tasks, {time.perf_counter() - t0:.1f} s)", file=stream)
    return out / "index.html"


def _check_destination(out: Path) -> None:
    if out.exists() and not out.is_dir():
        raise ReportError(f"report destination {out} exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not (out / MARKER).is_file():
        raise ReportError(f"report destination {out} is a non-empty folder that is not a cobgs report "
                          f"(no {MARKER}); refusing to replace it: choose another --out")


def _swap(tmp: Path, out: Path) -> None:
    """Put the finished ``tmp`` at ``out``: the old report is renamed away first, so at any
    moment ``out`` is either absent or a complete report."""
    old = None
    if out.exists():
        old = out.parent / f".{out.name}.old-{os.getpid()}"
        shutil.rmtree(old, ignore_errors=True)
        os.rename(out, old)
    os.rename(tmp, out)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


class _Logs:
    """Copies logs into ``logs/`` on first use and hands out their relative links."""

    def __init__(self, root: Path):
        self.root = root
        self.done: dict[Path, str] = {}

    def __call__(self, task: Optional[Task]) -> Optional[str]:
        if task is None or task.log_path is None or not Path(task.log_path).is_file():
            return None
        src = Path(task.log_path)
        if src in self.done:
            return self.done[src]
        name = f"{task.stage}-{slug(task.item_id)}-{fmt.short_key(task.key)}{'-failed' if task.state == 'failed' else ''}.log"
        dst = self.root / "logs" / name
        dst.parent.mkdir(parents=True, exist_ok=True)
        size = src.stat().st_size
        with open(src, "rb") as f, open(dst, "wb") as g:
            if size > LOG_TAIL_BYTES:
                f.seek(size - LOG_TAIL_BYTES)
                g.write(f"[report: log truncated to its last {LOG_TAIL_BYTES} of {size} bytes; full log: "
                        f"{src}]\n".encode())
            shutil.copyfileobj(f, g)
        self.done[src] = f"logs/{name}"
        return self.done[src]


# -- tables ------------------------------------------------------------------------------
def _cols_metrics() -> list[Column]:
    return [
        Column("iou", "mIoU", fmt.pct, better="max", title="mean IoU (%): over objects, then scenes"),
        Column("acc", "mAcc", fmt.pct, better="max", title="mean pixel accuracy (%)"),
        Column("biou", "mBIoU", fmt.pct, better="max", title="mean boundary IoU (%), width 2% of the diagonal"),
        Column("psnr", "PSNR", fmt.db, better="max", title="refined scene, held-out views (dB)"),
        Column("psnr_delta", "ΔPSNR", lambda v: fmt.db(v, signed=True), better="max",
               title="refined minus vanilla scene PSNR on the same views (dB)"),
        Column("num_gaussians", "Gaussians", fmt.count, title="scene size after the method (mean over objects)"),
        Column("refine_s", "Refine time", fmt.seconds, better="min", title="wall time of the method per object"),
        Column("peak_rss", "Peak RSS", fmt.nbytes,
               title="peak resident memory of the process that ran the refine task (host memory, max over "
                     "objects; with --jobs 1 this includes the driver's own footprint, so it is not ranked)"),
    ]


def _quoted(key: str, label: str, pct: bool = True) -> Column:
    return Column(key, label + " †", (lambda v: fmt.pct(v, 1)) if pct else fmt.db, quoted=True,
                  title="quoted from the paper, not measured here")


def _tables(data: RunData, infos: dict, logs: _Logs) -> dict:
    by_method, notes = R.method_records(data, infos, logs)
    by_scene = R.scene_method_records(data, infos, logs)
    paper_m = [c for c in (_quoted("paper_iou", "paper mIoU"), _quoted("paper_acc", "paper mAcc"))
               if any(c.key in r for r in by_method)]
    paper_s = [c for c in (_quoted("paper_iou", "paper mIoU"), _quoted("paper_biou", "paper mBIoU"),
                           _quoted("paper_psnr", "paper PSNR", pct=False)) if any(c.key in r for r in by_scene)]
    if paper_s and not notes:
        notes = ["Columns marked † are quoted from the paper (authors' runs on an RTX 3090), not measured "
                 "here; they never take part in best-value marking."]
    status = Column("status", "Status", numeric=False)
    t_method = build_table(
        "t-method", "Results by method: mean over objects within a scene, then over scenes",
        [Column("method", "Method", numeric=False, title="method item; below: its kind and the options that "
                "differ from the refine stage's defaults"), Column("scenes", "Scenes", fmt.count)]
        + _cols_metrics() + paper_m + [status], by_method,
        notes=notes + ["Best values are shaded and bold (among methods with every scene done; "
                       "not marked when all are equal)."])
    t_scene = build_table(
        "t-scene", "Results per scene × method (mean over the scene's objects); best per scene marked",
        [Column("scene", "Scene", numeric=False), Column("method", "Method", numeric=False),
         Column("objects", "Objects", fmt.count)] + _cols_metrics() + paper_s + [status], by_scene,
        group_by="scene", notes=[n for n in notes if paper_s])
    recs = R.object_records(data, infos, logs)
    for r in recs:  # best values per (scene, object): objects differ too much to compare across
        r["_group"] = f"{r['scene']}/{r['object']}"
    t_object = build_table(
        "t-object", "Per object: the evaluate stage's numbers and the refinement's Gaussian bookkeeping",
        [Column("scene", "Scene", numeric=False), Column("method", "Method", numeric=False),
         Column("object", "Object", numeric=False), Column("iou", "IoU", fmt.pct, better="max"),
         Column("acc", "Acc", fmt.pct, better="max"), Column("biou", "BIoU", fmt.pct, better="max"),
         *([Column("iou_object_only", "IoU obj. only", fmt.pct,
                   title="IoU of the object rendered alone (the released evaluation render), for reference; "
                         "the IoU column scores the visible mask")] if any(
             r.get("iou_object_only") is not None for r in recs) else []),
         Column("views", "Views", fmt.count, title="held-out views evaluated (hover for skipped ones)"),
         Column("psnr", "PSNR", fmt.db, better="max"), Column("psnr_delta", "ΔPSNR", lambda v: fmt.db(v, signed=True)),
         Column("num_gaussians", "Gaussians", fmt.count), Column("splits", "Splits", fmt.count),
         Column("pruned", "Pruned", fmt.count),
         Column("ambiguous_final", "Ambiguous", fmt.count, title="Gaussians with score < δ at the end, before RAEM"),
         Column("refine_s", "Refine time", fmt.seconds, better="min"), Column("peak_rss", "Peak RSS", fmt.nbytes),
         status], recs, group_by="_group")
    t_scenes = build_table(
        "t-scenes", "Scenes: data and the baseline 3DGS every method starts from",
        [Column("scene", "Scene", numeric=False), Column("kind", "Kind", numeric=False),
         Column("protocol", "Protocol", numeric=False), Column("scene_type", "Type", numeric=False),
         Column("views", "Views", fmt.count), Column("test_views", "Held out", fmt.count),
         Column("objects", "Objects", numeric=False), Column("iterations", "Iterations", fmt.count),
         Column("num_gaussians", "Gaussians", fmt.count), Column("train_s", "Train time", fmt.seconds),
         Column("psnr", "PSNR", fmt.db, title="vanilla scene, held-out views (dB)"),
         Column("ssim", "SSIM", lambda v: "" if fmt.finite(v) is None else f"{v:.4f}"),
         Column("status", "Training", numeric=False)], R.scene_records(data))
    return {"method": t_method, "scene": t_scene, "object": t_object, "scenes": t_scenes,
            "raw": {"by_method": by_method, "by_scene_method": by_scene}}


# -- pictures ----------------------------------------------------------------------------
#: segment's mask folder per ``mask_render`` of an evaluate row: the overlay must show the
#: mask that was scored (exact protocol: the visible mask; NVOS / LERF-mask: object only)
MASK_FOLDERS = {"visible": "pred_visible", "object_only": "pred_masks"}


def scored_mask_folder(row: Optional[dict]) -> str:
    return MASK_FOLDERS.get(str((row or {}).get("mask_render", "object_only")), "pred_masks")


def _pictures(data: RunData, infos: dict, root: Path) -> list[PictureSet]:
    ref = R.reference_method(infos)
    order = ([ref] if ref else []) + [m for m in data.methods if m != ref]
    sets = []
    pairs = []
    for r in data.results:
        if (r.scene, r.object) not in pairs:
            pairs.append((r.scene, r.object))
    for scene, obj in pairs:
        rs = {r.method: r for r in data.results if r.scene == scene and r.object == obj}
        held = data.scenes[scene].heldout.get(obj) if scene in data.scenes else None
        notes = []
        view, image, gt = None, None, None
        if held is not None:
            views = held.info.get("views") or []
            with_gt = [v for v in views if v.get("gt")]
            pick = (with_gt or views or [None])[0]
            if pick is not None:
                view = pick["name"]
                image = read_rgb(held.folder / pick["image"])
                gt = read_mask(held.folder / pick["gt"]) if pick.get("gt") else None
                notes.append(f"Held-out view {view}: the first of the {len(with_gt)} held-out view(s) with a "
                             f"ground-truth mask that the heldout stage wrote (not chosen by result).")
                if gt is None:
                    notes.append("No ground-truth mask for this view: no error overlay or crop.")
        else:
            notes.append("No held-out image or ground truth: the heldout stage has not run for this object "
                         f"(`cobgs run {data.workflow.path} --only heldout`); predicted masks and renders only.")
            for m in order:
                seg = rs[m].segment if m in rs else None
                if seg and seg.get("views"):
                    view = sorted(seg["views"])[0]
                    break
        if view is None:
            continue
        if any((r.row or {}).get("mask_render") == "visible" for r in rs.values()):
            notes.append("Predicted masks are the object's visible part (every Gaussian rendered, so "
                         "occluders hide the object as they do in the ground truth): the mask the "
                         "evaluate stage scored for this protocol.")
        ps = PictureSet(scene=scene, object=obj, view=view, notes=notes, id=slug(f"{scene}/{obj}"))
        preds, renders = {}, {}
        for m in order:
            if m not in rs:
                continue
            r = rs[m]
            mp = MethodPictures(m, infos[m].kind_label if m in infos else m)
            pv = r.per_view.get(view) or {}
            mp.iou, mp.biou = fmt.finite(pv.get("iou")), fmt.finite(pv.get("biou"))
            if r.segment_dir is not None:
                f = Path(r.segment_dir) / scored_mask_folder(r.row) / f"{view}.png"
                if f.is_file():
                    preds[m] = read_mask(f)
                for kind in ("object", "removed"):
                    f = Path(r.segment_dir) / kind / f"{view}.png"
                    if f.is_file():
                        renders.setdefault(m, {})[kind] = read_rgb(f)
            if m not in preds:
                p = r.problem
                mp.note = f"{p.state} at {p.stage}" if p else "no segmentation of this view"
            ps.methods.append(mp)
        base = f"img/{slug(scene)}/{slug(obj)}/{slug(view)}"
        compose(ps, image, gt, preds, renders, root / base, base)
        sets.append(ps)
    return sets


# -- plots -------------------------------------------------------------------------------
def _plots(data: RunData, infos: dict, by_method: list[dict], by_scene: list[dict], root: Path) -> dict:
    from . import plots as P

    ref = R.reference_method(infos)
    methods = [r["method"] for r in by_method]
    colors = P.method_colors(data.methods, ref)
    out: dict = dict.fromkeys(("iou_biou", "psnr", "time", "delta_sweep", "scores", "scores_skipped"))
    pts = {m: [(r.get("iou"), r.get("biou")) for r in by_scene if r["method"] == m and r.get("objects")]
           for m in methods}
    if len(data.scenes) < 2:
        pts = {}
    if P.iou_biou(root / "plots/iou_biou.svg", methods, [fmt.finite(r.get("iou")) for r in by_method],
                  [fmt.finite(r.get("biou")) for r in by_method], pts, colors):
        out["iou_biou"] = "plots/iou_biou.svg"
    vanilla = fmt.finite(_mean([r.get("psnr_vanilla") for r in by_method]))
    if P.psnr(root / "plots/psnr.svg", methods, [fmt.finite(r.get("psnr")) for r in by_method], vanilla, colors):
        out["psnr"] = "plots/psnr.svg"
    bars, stages = R.stage_time_bars(data)
    if P.time_breakdown(root / "plots/time.svg", bars, stages):
        out["time"] = "plots/time.svg"
    if P.delta_sweep(root / "plots/delta_sweep.svg", R.delta_groups(data, infos)):
        out["delta_sweep"] = "plots/delta_sweep.svg"
    panels, skipped = R.score_panels(data, ref)
    if P.score_curves(root / "plots/scores.svg", panels):
        out["scores"] = "plots/scores.svg"
        out["scores_skipped"] = skipped
    return out


def _mean(values) -> Optional[float]:
    vals = [v for v in (fmt.finite(x) for x in values) if v is not None]
    return sum(vals) / len(vals) if vals else None


# -- the page ----------------------------------------------------------------------------
def _env():
    import jinja2

    env = jinja2.Environment(loader=jinja2.FileSystemLoader(os.fspath(PACKAGE_DIR / "templates")),
                             autoescape=jinja2.select_autoescape(["html", "j2"]), undefined=jinja2.StrictUndefined,
                             trim_blocks=True, lstrip_blocks=True)
    env.filters.update(pct=fmt.pct, db=fmt.db, count=fmt.count, seconds=fmt.seconds, nbytes=fmt.nbytes,
                       timestamp=fmt.timestamp, short_key=fmt.short_key)
    return env


def _write(data: RunData, root: Path, sets: list[str]) -> None:
    from . import meta

    logs = _Logs(root)
    infos = R.method_infos(data)
    ref = R.reference_method(infos)
    tables = _tables(data, infos, logs)
    pictures = _pictures(data, infos, root)
    plots = _plots(data, infos, tables["raw"]["by_method"], tables["raw"]["by_scene_method"], root)
    stage_table = build_table(
        "t-refine-stages", f"Refinement stages of {ref}: ambiguous Gaussians and splits per stage",
        [Column("scene", "Scene", numeric=False), Column("object", "Object", numeric=False),
         Column("index", "Stage", fmt.count), Column("kind", "Kind", numeric=False),
         Column("iterations", "Iterations", fmt.count), Column("g_start", "Gaussians in", fmt.count),
         Column("g_end", "Gaussians out", fmt.count), Column("ambiguous", "Ambiguous", fmt.count),
         Column("ambiguous_large", "Ambiguous, splittable", fmt.count), Column("split", "Split", fmt.count),
         Column("pruned", "Pruned", fmt.count),
         Column("loss", "Mean loss", lambda v: "" if fmt.finite(v) is None else f"{v:.4f}"),
         Column("wall_s", "Time", fmt.seconds)], R.refine_stage_records(data, ref))
    task_table = build_table(
        "t-tasks", "Every task of the workflow: state, cache key, cost",
        [Column("order", "#", fmt.count), Column("stage", "Stage", numeric=False),
         Column("item", "Item", numeric=False), Column("state", "State", numeric=False),
         Column("key", "Cache key", fmt.short_key, numeric=False), Column("version", "v", fmt.count),
         Column("wall_s", "Wall", fmt.seconds), Column("cpu_s", "CPU", fmt.seconds),
         Column("peak_rss", "Peak RSS", fmt.nbytes), Column("host", "Host", numeric=False),
         Column("device", "Device", numeric=False), Column("started", "Started", fmt.timestamp),
         Column("log", "Log", numeric=False)], R.task_records(data, logs))
    failures = []
    for t in data.tasks:
        if t.state in ("failed", "corrupt"):
            failures.append({"stage": t.stage, "item": t.item_id, "state": t.state, "message": t.error,
                             "log": logs(t) if t.state == "failed" else None, "key": t.key})
    waiting = [{"stage": t.stage, "item": t.item_id, "state": t.state, "message": t.error}
               for t in data.tasks if t.state in ("missing", "stale")]
    skipped: dict = {}  # the protocol's own gaps (no / empty GT), the same for every method
    for r in data.results:
        for view, why in r.skipped.items():
            skipped.setdefault((r.scene, r.object), {})[view] = why
    eval_gaps = [{"scene": sc, "object": ob, "views": len(v), "reasons": ", ".join(
        f"{n}× {why}" for why, n in sorted(_count(v.values()).items())), "names": ", ".join(sorted(v))}
        for (sc, ob), v in skipped.items()]
    run = meta.run_metadata(data, sets)
    env_info = meta.report_environment()
    shutil.copytree(PACKAGE_DIR / "static", root / "static")
    (root / "workflow.toml").write_text(run["workflow"]["text"], encoding="utf-8")
    ctx = {
        "run": run, "env": env_info, "infos": infos, "reference": ref, "tables": tables, "pictures": pictures,
        "plots": plots, "stage_table": stage_table, "task_table": task_table, "failures": failures,
        "waiting": waiting, "eval_gaps": eval_gaps, "stages": meta.stage_records(data), "kind_labels": KIND_LABELS,
        "methods": data.methods, "n_results": len(data.results), "n_ok": sum(r.ok for r in data.results),
        "scenes": list(data.scenes),
    }
    html = _env().get_template("report.html.j2").render(**ctx)
    record = {"format": REPORT_FORMAT, "version": 1, "workflow": run["workflow"]["path"],
              "cache_dir": run["cache_dir"], "generated": env_info["generated"], "counts": run["counts"],
              "by_method": _plain(tables["raw"]["by_method"]),
              "by_scene_method": _plain(tables["raw"]["by_scene_method"]),
              "failures": failures, "plots": plots}
    (root / MARKER).write_text(json.dumps(record, indent=1, default=str) + "\n", encoding="utf-8")
    (root / "index.html").write_text(html, encoding="utf-8")  # last: the page is the report


def _count(values) -> dict:
    out: dict = {}
    for v in values:
        out[v] = out.get(v, 0) + 1
    return out


def _plain(records: list[dict]) -> list[dict]:
    """Records without the display-only keys (those starting with ``_``), NaN as null."""
    out = []
    for r in records:
        out.append({k: (fmt.finite(v) if isinstance(v, float) else v) for k, v in r.items() if not k.startswith("_")})
    return out
