"""``build_report``: one self-contained report folder from a workflow's cache.

The folder (``index.html``, ``static/``, ``img/``, ``plots/``, ``logs/``, ``workflow.toml``,
``report.json``, ``data/*.csv``, ``tables.md``: the result tables as Markdown) uses relative links only and no network resource, so it opens from
``file://`` anywhere it is copied. It is written to a temporary sibling folder and swapped
into place as a whole (:func:`pipeline.publish.publish_folder`), so a kill leaves either the
previous report or the new one; an existing report at the destination is replaced, any other
non-empty folder is refused.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path
from typing import Iterable, Optional, Sequence

from cobgs.configs import Files
from pipeline.publish import DestinationError, check_apart, check_destination, publish_folder

from . import fmt, methods, plotdata
from .methods import reference_of
from .collect import RunData, TaskRecord, collect
from .errors import ReportError
from .gallery import picture_sets
from .pictures import KIND_LABELS, slug
from .sections import detail_tables, result_tables
from .tables import to_markdown

MARKER = Files.REPORT_MARKER
REPORT_FORMAT = "cobgs-report"
LOG_TAIL_BYTES = 1 << 20  # logs above this keep their last MiB (the end holds the traceback)
PACKAGE_DIR = Path(__file__).resolve().parent


def default_out_dir(workflow) -> Path:
    return Path("runs") / "reports" / workflow.name


def build_report(workflow_path: os.PathLike | str, out_dir: Optional[os.PathLike | str] = None,
                 cache_dir: Optional[os.PathLike | str] = None, sets: Iterable[str] = (),
                 registry=None, stream=None, turntables: int = 0, viewer: bool = True,
                 viewer_mb: Optional[float] = None, scene_cameras=None,
                 trajectories: Optional[os.PathLike | str] = None, replace: bool = False) -> Path:
    """Build the report of a workflow from its cache; returns the path of ``index.html``.

    Args:
        workflow_path: the workflow TOML file.
        out_dir: report folder (default ``runs/reports/<workflow name>``).
        cache_dir: cache folder (default: ``$COBGS_CACHE_DIR``, else ``runs/cache``).
        sets: ``--set`` overrides, as for ``cobgs run`` (they select the cache entries).
        registry: the stage registry (required; the command layer hands in the program's:
            :func:`stages.commands.report.build_report`).
        scene_cameras: ``(dataset dir, poses dir) -> (cameras, background)`` of a scene,
            for turntables and the 3D viewers (the command layer hands in the stages' reader).
        stream: where to print progress lines (None: quiet).
        turntables: frames of an orbit GIF per method and object (object alone, scene
            without it; rendered on the CPU while building): 0 = none.
        viewer: embed the 3D splat viewers (quantised Gaussians of every segmentation,
            ``static/viewer.js``); False for a small report.
        viewer_mb: cap of the viewer payload per scene in MB (default
            :data:`reports.viewer.DEFAULT_MAX_MB`); a scene over it is subsampled.
        trajectories: a folder of ``tests/benchmarks/bm_refine_trajectory.py`` records: the
            refinement section draws, per scene of the run, IoU / boundary IoU after every stage
            (:mod:`reports.trajectory`; records of other scenes are left out).
        replace: replace an earlier report at ``out_dir`` even where files were added to it.
            Without it such a folder is refused, naming the files; a folder that is no report
            of cobgs is always refused (:func:`pipeline.publish.check_destination`).
    """
    from pipeline import load_workflow
    from pipeline.cache import default_cache_dir

    if registry is None:
        raise ReportError("build_report needs the stage registry (the command layer hands it in: "
                          "stages.commands.report.build_report does)")
    sets = list(sets)
    wf = load_workflow(workflow_path, registry, sets=sets)
    cache = Path(default_cache_dir(os.fspath(cache_dir) if cache_dir else None))
    if not cache.is_dir():
        raise ReportError(f"workflow {wf.name!r}: cache folder {cache} does not exist; run "
                          f"`cobgs run {workflow_path}` first or pass --cache-dir")
    out = Path(out_dir) if out_dir else default_out_dir(wf)
    try:
        check_apart(out, cache, "report")
    except DestinationError as exc:
        raise ReportError(str(exc)) from None
    _check_destination(out, replace)
    t0 = time.perf_counter()
    data = collect(wf, cache)
    data.scene_cameras = scene_cameras
    records = []
    if trajectories is not None:  # read (and checked) before anything is written
        from .trajectory import load_trajectories

        records = load_trajectories(trajectories, data.scenes)
    try:
        publish_folder(out, lambda tmp: _write(data, tmp, sets, turntables, viewer, viewer_mb, records), MARKER,
                       "report", replace=replace)
    except DestinationError as exc:
        raise ReportError(str(exc)) from None
    if stream is not None:
        print(f"report of {wf.name}: {out / 'index.html'} ({len(data.results)} results, "
              f"{len(data.failed)} failed tasks, {time.perf_counter() - t0:.1f} s)", file=stream)
    return out / "index.html"


def _check_destination(out: Path, replace: bool = False) -> None:
    """Before any work: a destination that is not a cobgs report is refused."""
    try:
        check_destination(out, MARKER, "report", replace=replace)
    except DestinationError as exc:
        raise ReportError(str(exc)) from None


class _Logs:
    """Copies logs into ``logs/`` on first use and hands out their relative links."""

    def __init__(self, root: Path):
        self.root = root
        self.done: dict[Path, str] = {}

    def __call__(self, task: Optional[TaskRecord]) -> Optional[str]:
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


# -- plots -------------------------------------------------------------------------------
def _plots(data: RunData, infos: dict, by_method: list[dict], by_scene: list[dict], root: Path) -> dict:
    from . import plots as P

    ref = reference_of(infos)
    methods = [r["method"] for r in by_method]
    colors = P.method_colors(data.methods, ref)
    out: dict = dict.fromkeys(("iou_biou", "psnr", "time", "delta_sweep", "scores", "scores_skipped", "incomplete"))
    pts = {m: [(r.get("iou"), r.get("biou")) for r in by_scene if r["method"] == m and r.get("objects")]
           for m in methods}
    if len(data.scenes) < 2:
        pts = {}
    # "*": the method misses some scene or object, so its mean covers fewer (as in the table)
    labels = [r["method"] + ("*" if r.get("_nobest") else "") for r in by_method]
    out["incomplete"] = [r["method"] for r in by_method if r.get("_nobest")]
    if P.iou_biou(root / "plots/iou_biou.svg", methods, [fmt.finite(r.get("iou")) for r in by_method],
                  [fmt.finite(r.get("biou")) for r in by_method], pts, colors, labels):
        out["iou_biou"] = "plots/iou_biou.svg"
    vanilla = [fmt.finite(r.get("psnr_vanilla")) for r in by_method]  # each method's own scenes
    if P.psnr(root / "plots/psnr.svg", methods, [fmt.finite(r.get("psnr")) for r in by_method], vanilla, colors,
              labels):
        out["psnr"] = "plots/psnr.svg"
    bars, stages = plotdata.stage_time_bars(data)
    if P.time_breakdown(root / "plots/time.svg", bars, stages):
        out["time"] = "plots/time.svg"
    if P.delta_sweep(root / "plots/delta_sweep.svg", plotdata.delta_groups(data, infos), plotdata.FIXED_DELTA):
        out["delta_sweep"] = "plots/delta_sweep.svg"
    panels, skipped = plotdata.score_panels(data, ref)
    if P.score_curves(root / "plots/scores.svg", panels):
        out["scores"] = "plots/scores.svg"
        out["scores_skipped"] = skipped
    return out


def _trajectory_plots(data: RunData, ref: Optional[str], records: Sequence[dict], root: Path) -> list[dict]:
    """One figure per scene with trajectory records: [{scene, path, records: [file names]}]."""
    from . import plots as P
    from .trajectory import by_scene

    if not records:
        return []
    methods = list(data.methods) + sorted({r["method"] for r in records} - set(data.methods))
    colors = P.method_colors(methods, ref)
    out = []
    for scene, recs in sorted(by_scene(list(records)).items()):
        rel = f"plots/trajectory-{slug(scene)}.svg"
        if P.trajectory(root / rel, scene, recs, colors):
            out.append({"scene": scene, "path": rel, "records": [r["path"].name for r in recs]})
    return out


# -- the page ----------------------------------------------------------------------------
def _env():
    import jinja2

    env = jinja2.Environment(loader=jinja2.FileSystemLoader(os.fspath(PACKAGE_DIR / "templates")),
                             autoescape=jinja2.select_autoescape(["html", "j2"]), undefined=jinja2.StrictUndefined,
                             trim_blocks=True, lstrip_blocks=True)
    env.filters.update(pct=fmt.pct, db=fmt.db, count=fmt.count, seconds=fmt.seconds, nbytes=fmt.nbytes,
                       timestamp=fmt.timestamp, short_key=fmt.short_key)
    return env


def _write(data: RunData, root: Path, sets: list[str], turntables: int = 0, viewer: bool = True,
           viewer_mb: Optional[float] = None, trajectories: Sequence[dict] = ()) -> None:
    from . import meta
    from .viewer import DEFAULT_MAX_MB, viewer_sets

    logs = _Logs(root)
    infos = methods.method_infos(data)
    ref = reference_of(infos)
    tables = result_tables(data, infos, logs)
    pictures = picture_sets(data, infos, root, turntables)
    viewers = viewer_sets(data, pictures, root, DEFAULT_MAX_MB if viewer_mb is None else viewer_mb) if viewer else {}
    plots = _plots(data, infos, tables["raw"]["by_method"], tables["raw"]["by_scene_method"], root)
    plots["trajectories"] = _trajectory_plots(data, ref, trajectories, root)
    stage_table, task_table = detail_tables(data, ref, logs)
    failures = []
    for t in data.tasks:
        if t.state in ("failed", "corrupt"):
            failures.append({"stage": t.stage, "item": t.item_id, "state": t.state, "message": t.error,
                             "log": logs(t) if t.state == "failed" else None, "key": t.key})
    waiting = [{"stage": t.stage, "item": t.item_id, "state": t.state, "message": t.error}
               for t in data.tasks if t.state in ("missing", "stale")]
    skipped: dict = {}  # the protocol's own gaps (no / empty GT), per scene and object
    for r in data.results:
        for view, why in r.skipped.items():
            skipped.setdefault((r.scene, r.object), {})[view] = why
        for view, why in r.empty_gt.items():  # LERF-mask: an empty GT scored 0 (per method)
            if view not in r.skipped:
                skipped.setdefault((r.scene, r.object), {})[f"{view} ({r.method})"] = why
    eval_gaps = [{"scene": sc, "object": ob, "views": len(v), "reasons": ", ".join(
        f"{n}× {why}" for why, n in sorted(_count(v.values()).items())), "names": ", ".join(sorted(v))}
        for (sc, ob), v in skipped.items()]
    run = meta.run_metadata(data, sets)
    env_info = meta.report_environment()
    shutil.copytree(PACKAGE_DIR / "static", root / "static")
    (root / "workflow.toml").write_text(run["workflow"]["text"], encoding="utf-8")
    ctx = {
        "run": run, "env": env_info, "infos": infos, "reference": ref, "tables": tables, "pictures": pictures,
        "picture_scenes": _by_scene(pictures), "viewers": viewers,
        "plots": plots, "stage_table": stage_table, "task_table": task_table, "failures": failures,
        "waiting": waiting, "eval_gaps": eval_gaps, "stages": meta.stage_records(data), "kind_labels": KIND_LABELS,
        "methods": data.methods, "n_results": len(data.results), "n_ok": sum(r.ok for r in data.results),
        "scenes": list(data.scenes),
        "warnings": [{"scene": r.scene, "method": r.method, "object": r.object, "message": m}
                     for r in data.results for m in (r.row or {}).get("warnings") or []],
    }
    html = _env().get_template("report.html.j2").render(**ctx)
    record = {"format": REPORT_FORMAT, "version": 1, "workflow": run["workflow"]["path"],
              "cache_dir": run["cache_dir"], "generated": env_info["generated"], "counts": run["counts"],
              "tasks_window": {k: run[k] for k in ("started", "finished", "wall_s", "cpu_s", "hosts")},
              "reference": ref,  # the method data/differences.csv subtracts the others from
              "by_method": _plain(tables["raw"]["by_method"]),
              "by_scene_method": _plain(tables["raw"]["by_scene_method"]),
              "failures": failures, "plots": plots}
    for name, recs in tables["raw"].items():  # the tables as data, for an appendix's own typesetting
        _write_csv(root / "data" / f"{name}.csv", _plain(recs))
    wf_path = os.path.relpath(data.workflow.path) if not os.path.relpath(data.workflow.path).startswith("..") \
        else os.fspath(data.workflow.path)
    md = [f"# {data.workflow.name}: result tables", "",
          f"From `cobgs report {wf_path}` ({fmt.timestamp(env_info['generated'])}); the same numbers as index.html, "
          "means as the summary stage (over objects within a scene, then over scenes). Bold: best in its group.", ""]
    for key in ("method", "scene", "spin", "diff", "ablation", "psnr", "scenes"):
        if tables.get(key) is not None:
            md += [to_markdown(tables[key]), ""]
    (root / "tables.md").write_text("\n".join(md), encoding="utf-8")
    (root / MARKER).write_text(json.dumps(record, indent=1, default=str) + "\n", encoding="utf-8")
    (root / "index.html").write_text(html, encoding="utf-8")  # last: the page is the report


def _write_csv(path: Path, rows: list[dict]) -> None:
    import csv

    path.parent.mkdir(parents=True, exist_ok=True)
    keys: list[str] = []
    for r in rows:
        keys += [k for k, v in r.items() if k not in keys and not isinstance(v, (dict, list))]
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.DictWriter(f, fieldnames=keys, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: "" if r.get(k) is None else r.get(k) for k in keys})


def _count(values) -> dict:
    out: dict = {}
    for v in values:
        out[v] = out.get(v, 0) + 1
    return out


def _by_scene(pictures: list) -> list[tuple[str, list]]:
    """[(scene, its picture sets)] in the order the sets come (scene order)."""
    out: dict[str, list] = {}
    for ps in pictures:
        out.setdefault(ps.scene, []).append(ps)
    return list(out.items())


def _plain(records: list[dict]) -> list[dict]:
    """Records without the display-only keys (those starting with ``_``), NaN as null."""
    out = []
    for r in records:
        out.append({k: (fmt.finite(v) if isinstance(v, float) else v) for k, v in r.items() if not k.startswith("_")})
    return out
