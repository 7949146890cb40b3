"""``cobgs export WORKFLOW --to DIR``: copy a workflow's results out of the cache.

Layout written (README "Exports")::

    DIR/summary.json, summary.csv, by_method.csv, by_scene_method.csv, timings.csv, scenes.csv
    DIR/<scene>/scene.ply                         trained 3DGS scene (standard layout)
    DIR/<scene>/train.json
    DIR/<scene>/<method>/<object>/refined.ply     scene after the method, with label extras
    DIR/<scene>/<method>/<object>/object.ply      the object (standard 3DGS layout)
    DIR/<scene>/<method>/<object>/background.ply  the scene without the object
    DIR/<scene>/<method>/<object>/metrics.json
    DIR/export.json                               what was copied from which cache entry

Only finished entries of the workflow's *current* configuration are copied (what
``cobgs status`` calls done); anything else is listed as missing. Each file is copied to a
temporary name and renamed, so a file in DIR is always complete.
"""

from __future__ import annotations

import os

# (stage, artifact, files inside it, destination relative to <scene>[/<method>/<object>])
EXPORTS = (
    ("train", "scene", ("scene.ply", "train.json"), "scene"),
    ("refine", "refined", ("refined.ply",), "object"),
    ("segment", "segmentation", ("object.ply", "background.ply"), "object"),
    ("evaluate", "metrics", ("metrics.json",), "object"),
    ("summary", "summary", ("summary.json", "summary.csv", "by_method.csv", "by_scene_method.csv",
                            "timings.csv", "scenes.csv"), "root"),
)


def _copy(src, dst) -> None:
    import shutil

    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = dst.with_name(f".{dst.name}.{os.getpid()}.tmp")
    shutil.copyfile(src, tmp)
    os.replace(tmp, dst)


def export(workflow, cache_dir, to, stream=None) -> dict:
    """Copy the exports of ``workflow`` (a loaded :class:`pipeline.Workflow`) from
    ``cache_dir`` into ``to``; returns the record written to ``export.json``."""
    import json
    from pathlib import Path

    from pipeline import entries

    to = Path(to)
    wanted = {stage: (artifact, files, where) for stage, artifact, files, where in EXPORTS}
    copied, missing = [], []
    for rec in entries(workflow, cache_dir):
        if rec.stage not in wanted:
            continue
        artifact, files, where = wanted[rec.stage]
        v = rec.item.values
        if where == "scene":
            dest = to / v["scene"]
        elif where == "object":
            dest = to / v["scene"] / v["method"] / v["object"]
        else:
            dest = to
        if rec.state != "done":
            missing.append({"stage": rec.stage, "item": rec.item.id, "state": rec.state,
                            "reasons": list(getattr(rec, "reasons", []) or [])})
            continue
        folder = Path(rec.output(artifact))
        for name in files:
            _copy(folder / name, dest / name)
            copied.append({"file": str((dest / name).relative_to(to)), "stage": rec.stage,
                           "item": rec.item.id, "entry": str(folder)})
    record = {"workflow": str(workflow.path), "cache_dir": str(Path(cache_dir).resolve()),
              "copied": copied, "missing": missing}
    tmp = to / f".export.json.{os.getpid()}.tmp"
    to.mkdir(parents=True, exist_ok=True)
    tmp.write_text(json.dumps(record, indent=1))
    os.replace(tmp, to / "export.json")
    return record


def _run(args) -> int:
    import sys

    from pipeline import PipelineError, load_workflow
    from pipeline.commands import default_cache_dir
    from stages.registry import load_registry

    try:
        wf = load_workflow(args.workflow, load_registry(), args.set or [])
    except PipelineError as exc:
        print(f"cobgs export: {exc}", file=sys.stderr)
        return 2
    cache = default_cache_dir(args.cache_dir)
    print(f"cache: {cache}")
    rec = export(wf, cache, args.to)
    for m in rec["missing"]:
        print(f"  not exported: {m['stage']} {m['item'] or '(workflow)'} ({m['state']})", file=sys.stderr)
    plys = [c["file"] for c in rec["copied"] if c["file"].endswith(".ply")]
    dest = os.path.abspath(args.to)
    print(f"exported {len(rec['copied'])} files ({len(plys)} PLYs) to {dest}")
    _print_summary(os.path.join(dest, "summary.json"), dest)
    if not rec["copied"]:
        print("nothing to export: run the workflow first (`cobgs run ...`)", file=sys.stderr)
        return 1
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

    print(f"\n{'method':<14} {'mIoU':>7} {'mBIoU':>7} {'mAcc':>7} {'obj-only':>8} {'PSNR dB':>8} {'vanilla':>8}"
          "  objects")
    for r in data.get("by_method", []):
        print(f"{r['method']:<14} {fmt(r.get('iou'), '.4f'):>7} {fmt(r.get('biou'), '.4f'):>7} "
              f"{fmt(r.get('acc'), '.4f'):>7} {fmt(r.get('iou_object_only'), '.4f'):>8} "
              f"{fmt(r.get('psnr'), '.2f'):>8} "
              f"{fmt(r.get('psnr_vanilla'), '.2f'):>8}  {r.get('objects')}")
    for s in data.get("scenes", []):
        print(f"scene {s['scene']}: {s['num_gaussians']} Gaussians, held-out PSNR "
              f"{fmt(s.get('psnr'), '.2f')} dB ({s['test_views']} views)")
    print("mIoU: the object's visible mask (exact GT) or the protocol's render (NVOS, LERF-mask); "
          "obj-only: the released object-only render")
    print(f"summary: {os.path.join(dest, 'summary.csv')} (rows), by_method.csv, timings.csv")
    print(f"PLYs:    {dest}/<scene>/scene.ply, {dest}/<scene>/<method>/<object>/"
          "{refined,object,background}.ply")


def register(sub) -> None:
    p = sub.add_parser("export", help="copy a workflow's PLYs, metrics and summary out of the cache",
                       description="Copy the trained scene, refined scene, object and background PLYs, "
                       "metrics and summary of every finished task of WORKFLOW into DIR "
                       "(DIR/<scene>/<method>/<object>/...).")
    p.add_argument("workflow", help="workflow TOML file")
    p.add_argument("--to", required=True, metavar="DIR", help="destination folder (created)")
    p.add_argument("--set", action="append", metavar="K=V", help="same overrides as `cobgs run`")
    p.add_argument("--cache-dir", default=None, help="cache folder (default: $COBGS_CACHE_DIR or ./runs/cache)")
    p.set_defaults(func=_run)
