"""``cobgs export WORKFLOW --to DIR``: copy a workflow's results out of the cache.

Layout written (README "Exports")::

    DIR/summary.json, summary.csv, by_method.csv, by_scene_method.csv, timings.csv, scenes.csv
    DIR/<scene>/scene.ply                         trained 3DGS scene (standard layout)
    DIR/<scene>/train.json
    DIR/<scene>/<method>/<object>/refined.ply     scene after the method, with label extras
    DIR/<scene>/<method>/<object>/object.ply      the object (standard 3DGS layout)
    DIR/<scene>/<method>/<object>/background.ply  the scene without the object
    DIR/<scene>/<method>/<object>/metrics.json
    DIR/<scene>/<method>/<object>/pred_masks/<view>.png  the 2D predicted masks (held-out views)
    DIR/export.json                               what was copied from which cache entry

Only finished entries of the workflow's *current* configuration are copied (what
``cobgs status`` calls done); anything else is listed as missing. DIR is built beside itself
and swapped into place as a whole: a kill leaves the previous export or the new one.
"""

from __future__ import annotations

from cobgs.configs import Files
import os

# (stage, artifact, files inside it, destination relative to <scene>[/<method>/<object>])
EXPORTS = (
    ("train", "scene", (Files.SCENE_PLY, Files.TRAIN), "scene"),
    ("refine", "refined", (Files.REFINED_PLY,), "object"),
    ("segment", "segmentation", (Files.OBJECT_PLY, Files.BACKGROUND_PLY, Files.PRED_MASKS), "object"),
    ("evaluate", "metrics", (Files.METRICS,), "object"),
    ("summary", "summary", (Files.SUMMARY, Files.SUMMARY_CSV, Files.BY_METHOD, Files.BY_SCENE_METHOD,
                            Files.TIMINGS, Files.SCENES), "root"),
)


def _copy(src, dst) -> None:
    import shutil

    dst.parent.mkdir(parents=True, exist_ok=True)
    if src.is_dir():  # a folder of files (the 2D predicted masks)
        shutil.copytree(src, dst)
    else:
        shutil.copyfile(src, dst)


def _size(path) -> int:
    from pipeline.cache import dir_size

    return dir_size(path) if path.is_dir() else (path.stat().st_size if path.exists() else 0)


def _human(n: int) -> str:
    return f"{n / 2**30:.1f} GiB" if n >= 1 << 30 else f"{n / 2**20:.1f} MiB"


#: A turntable GIF frame of an object, bounded (the renders are at most the dataset's size,
#: palette-coded): the estimate the free-space check uses.
TURNTABLE_FRAME_BYTES = 256 << 10


def export_bytes(plan, objects_with_turntables: int, turntables: int) -> int:
    """What an export writes: the files it copies, two turntable GIFs per object, and its
    export.json (a few KiB per file)."""
    files = sum(_size(src) for src, _, _ in plan)
    gifs = 2 * objects_with_turntables * turntables * TURNTABLE_FRAME_BYTES
    return files + gifs + 4096 * (len(plan) + 1)


def export(workflow, cache_dir, to, stream=None, ply: bool = True, turntables: int = 0,
           replace: bool = False) -> dict:
    """Copy the exports of ``workflow`` (a loaded :class:`pipeline.Workflow`) from
    ``cache_dir`` into ``to``; returns the record written to ``export.json``.

    ``ply=False`` leaves the PLYs in the cache (metrics, masks and summary only: a
    benchmark's hundreds of scenes are tens of GB). ``turntables=N`` adds, per object, an
    N-frame orbit GIF of the object alone and of the scene without it
    (``turntable_object.gif``, ``turntable_removed.gif``; :mod:`cobgs.render.turntable`). A copy the destination's disk cannot
    hold (with a margin of 4 MiB + 10 %, at most 1 GiB) is refused before anything is written,
    saying what it needs and what is free.

    ``to`` is replaced as a whole (:func:`pipeline.publish.publish_folder`): a kill leaves
    the previous export or the new one, never a mix. It may be absent, empty or an earlier
    export (its ``export.json`` was written by cobgs); another folder is refused, and so is an
    earlier export that holds files cobgs did not write unless ``replace``. With nothing of
    the workflow done, nothing is written (PipelineError)."""
    import json
    from pathlib import Path

    from pipeline import entries
    from pipeline.publish import check_apart, check_destination, publish_folder

    to = Path(os.path.abspath(to))
    check_apart(to, Path(cache_dir), "export")
    check_destination(to, Files.EXPORT_MARKER, "export", replace=replace)
    wanted = {stage: (artifact, files, where) for stage, artifact, files, where in EXPORTS}
    plan, missing = [], []
    scenes: dict = {}
    segments = []
    for rec in entries(workflow, cache_dir):
        if rec.state == "done" and rec.stage in ("dataset", "sfm"):
            scenes.setdefault(rec.item.values.get("scene"), {})[rec.stage] = rec
        if rec.state == "done" and rec.stage == "segment":
            segments.append(rec)
        if rec.stage not in wanted:
            continue
        artifact, files, where = wanted[rec.stage]
        v = rec.item.values
        parts = {"scene": (v.get("scene"),), "object": (v.get("scene"), v.get("method"), v.get("object")),
                 "root": ()}[where]
        if rec.state != "done":
            missing.append({"stage": rec.stage, "item": rec.item.id, "state": rec.state,
                            "reasons": list(getattr(rec, "reasons", []) or [])})
            continue
        folder = Path(rec.output(artifact))
        for name in files:
            if ply or not name.endswith(".ply"):
                plan.append((folder / name, Path(*parts, name), rec))
    import shutil

    if not plan:
        from pipeline.errors import PipelineError

        raise PipelineError(f"nothing to export: no task of workflow {workflow.name!r} is done in the cache "
                            f"{Path(cache_dir).resolve()} ({len(missing)} not done); run `cobgs run "
                            f"{workflow.path}` first (with the same --set and --cache-dir). {to} was left as it was")
    need = export_bytes(plan, len(segments) if turntables > 0 else 0, turntables)
    probe = to.parent if not to.exists() else to
    while not probe.exists():
        probe = probe.parent
    free = shutil.disk_usage(probe).free
    spare = min(1 << 30, (4 << 20) + need // 10)  # a margin that scales with the export
    if need + spare > free:
        from pipeline.errors import PipelineError

        ply_bytes = sum(_size(src) for src, _, _ in plan if src.name.endswith(".ply"))
        hint = ("use --no-ply to leave the PLYs in the cache, or another --to" if ply and ply_bytes
                else "free some space or choose another --to")
        raise PipelineError(f"the export needs {_human(need)} (+ {_human(spare)} kept spare) but {probe} has "
                            f"{_human(free)} free; {hint}")
    copied = []

    def write(tmp: Path) -> None:
        for src, rel, rec in plan:
            dst = tmp / rel
            # item names are checked when the workflow loads; never write outside the folder
            if os.path.commonpath([os.path.abspath(dst), str(tmp)]) != str(tmp) or ".." in rel.parts:
                raise ValueError(f"export path {rel} would leave the export folder")
            _copy(src, dst)
            copied.append({"file": rel.as_posix(), "stage": rec.stage, "item": rec.item.id,
                           "entry": str(src.parent)})
        from cobgs.render.turntable import object_turntables
        from stages._common import scene_cameras

        cameras: dict = {}  # scene -> (cameras, background): each scene loaded once
        for rec in segments if turntables > 0 else ():
            v = rec.item.values
            sc = scenes.get(v.get("scene"), {})
            if "dataset" not in sc:
                continue
            if v.get("scene") not in cameras:
                poses = sc["sfm"].output("poses") if "sfm" in sc else None
                cameras[v.get("scene")] = scene_cameras(sc["dataset"].output("dataset"), poses)
            refs, bg = cameras[v.get("scene")]
            rel = Path(v.get("scene"), v.get("method"), v.get("object"))
            names = {k: f"turntable_{k}.gif" for k in ("object", "removed")}
            seg = rec.output("segmentation")
            for kind in object_turntables(seg / Files.OBJECT_PLY, seg / Files.BACKGROUND_PLY, refs, bg, turntables,
                                          {k: tmp / rel / n for k, n in names.items()}):
                copied.append({"file": (rel / names[kind]).as_posix(), "stage": "segment", "item": rec.item.id,
                               "entry": "rendered by cobgs.render.turntable"})
        record.update(copied=copied)
        (tmp / Files.EXPORT_MARKER).write_text(json.dumps(record, indent=1))

    record = {"workflow": str(workflow.path), "cache_dir": str(Path(cache_dir).resolve()),
              "copied": copied, "missing": missing}
    publish_folder(to, write, Files.EXPORT_MARKER, "export", replace=replace)
    return record


def _run(args) -> int:
    import sys

    from pipeline import PipelineError, load_workflow
    from pipeline.cache import default_cache_dir
    from stages.registry import load_registry

    try:
        wf = load_workflow(args.workflow, load_registry(), args.sets)
    except PipelineError as exc:
        print(f"cobgs export: {exc}", file=sys.stderr)
        return 2
    cache = default_cache_dir(args.cache_dir)
    print(f"cache: {cache}")
    try:
        rec = export(wf, cache, args.to, ply=not args.no_ply, turntables=args.turntables, replace=args.replace)
    except PipelineError as exc:
        print(f"cobgs export: {exc}", file=sys.stderr)
        return 2
    for m in rec["missing"]:
        print(f"  not exported: {m['stage']} {m['item'] or '(workflow)'} ({m['state']})", file=sys.stderr)
    plys = [c["file"] for c in rec["copied"] if c["file"].endswith(".ply")]
    dest = os.path.abspath(args.to)
    print(f"exported {len(rec['copied'])} files ({len(plys)} PLYs) to {dest}")
    _print_summary(os.path.join(dest, Files.SUMMARY), dest)
    return 1 if rec["missing"] else 0


def _print_summary(path: str, dest: str) -> None:
    """The per-method means and where the files are, for a human at the terminal."""
    import json
    import math

    if not os.path.isfile(path):
        return
    with open(path, encoding="utf-8") as f:
        data = json.load(f)

    def fmt(v, spec):
        return "n/a" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, spec)

    print(f"\n{'method':<14} {'mIoU':>7} {'mBIoU':>7} {'mAcc':>7} {'BIoU rel':>8} {'BIoU occ':>8} {'PSNR dB':>8} "
          f"{'pre-RAEM':>8} {'vanilla':>8}  objects   (mIoU / mBIoU / mAcc: the headline protocol)")
    for r in data.get("by_method", []):
        print(f"{r['method']:<14} {fmt(r.get('iou'), '.4f'):>7} {fmt(r.get('biou'), '.4f'):>7} "
              f"{fmt(r.get('acc'), '.4f'):>7} {fmt(r.get('biou_released'), '.4f'):>8} "
              f"{fmt(r.get('biou_occlusion'), '.4f'):>8} {fmt(r.get('psnr'), '.2f'):>8} "
              f"{fmt(r.get('psnr_before_raem'), '.2f'):>8} "
              f"{fmt(r.get('psnr_vanilla'), '.2f'):>8}  {r.get('objects')}")
    for w in data.get("warnings") or []:
        print(f"WARNING {w['item']}: {w['message']}")
    if any(r.get("protocol") == "none" for r in data.get("rows", [])):
        print("mIoU n/a: the held-out views have no ground-truth masks (your own data): only the "
              "PSNR columns and the pictures say how the segmentation went")
    for s in data.get("scenes", []):
        print(f"scene {s['scene']}: {s['num_gaussians']} Gaussians, held-out PSNR "
              f"{fmt(s.get('psnr'), '.2f')} dB ({s['test_views']} views)")
    print("mIoU / mBIoU / mAcc: the headline protocol (the object's Gaussians rendered alone vs its whole "
          "silhouette where the data has it, else the visible GT; NVOS / LERF-mask: their own); BIoU rel: the "
          "same render vs the visible GT (released protocol); BIoU occ: the occlusion-aware render")
    print(f"summary: {os.path.join(dest, 'summary.csv')} (rows), by_method.csv, timings.csv")
    print(f"PLYs:    {dest}/<scene>/scene.ply, {dest}/<scene>/<method>/<object>/"
          "{refined,object,background}.ply")


def register(sub) -> None:
    from . import frame_count

    p = sub.add_parser("export", help="copy a workflow's PLYs, metrics and summary out of the cache",
                       description="Copy the trained scene, refined scene, object and background PLYs, "
                       "metrics and summary of every finished task of WORKFLOW into DIR "
                       "(DIR/<scene>/<method>/<object>/...).")
    p.add_argument("workflow", help="workflow TOML file")
    p.add_argument("--to", required=True, metavar="DIR",
                   help="destination folder (created). It must be absent, empty or an earlier export of cobgs: "
                        "that export is replaced as a whole. Any other folder is refused, and so is an earlier "
                        "export that holds files cobgs did not write, unless --replace is given")
    p.add_argument("--replace", action="store_true",
                   help="replace an earlier export of cobgs even where files were added to it (they are deleted)")
    from pipeline.commands import add_cache_dir, add_sets

    add_sets(p)
    add_cache_dir(p)
    p.add_argument("--no-ply", action="store_true",
                   help="metrics, masks and summary only: leave the PLYs in the cache (large workflows)")
    p.add_argument("--turntables", type=frame_count, default=0, metavar="N",
                   help="per object, N-frame orbit GIFs of the object alone and of the scene without it "
                        "(rendered on the CPU; 0 = none)")
    p.set_defaults(func=_run)
