"""Stage ``summary``: one table over every scene x method x object of a workflow.

It gathers every ``metrics`` artifact (and every trained ``scene``, for scenes evaluated
on texture only) and, walking the provenance of each (the cache
manifests), the entries of every stage that fed it, so that a report can be built from
this artifact plus the manifests alone.

Output ``summary``:
  summary.json          rows (one per scene x method x object: the evaluate row plus the
                        cache entries of each stage that made it; where the workflow sweeps
                        FlashSplat's bias, ``flashsplat_oracle`` rows copy the best item's
                        per scene, ``oracle_choice`` naming it), aggregates per scene x
                        method and per method (mean over objects, then over scenes: NVOS's
                        mean over tasks and LERF-mask's mean over prompts), per-stage timings
  summary.csv           the rows
  by_method.csv, by_scene_method.csv   the aggregates
  timings.csv           one line per cache entry used: stage, item, wall / CPU time, peak RSS
  scenes.csv            per scene: the trained scene's held-out PSNR / SSIM, Gaussians, time
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

from cobgs.configs import Files, check_params
from pipeline import Resources, Stage

from ._common import read_json, write_json

# (results only: timings come from the manifests, into timings.csv / scenes.csv)
from cobgs.evaluate.names import METRICS  # noqa: E402 (imports nothing)


@dataclass(frozen=True)
class SummaryParams:
    """Attributes:
        target_miou: a bar to check the overall object mIoU of every method against
            (recorded as ``meets_target`` per method; 0 = none).
    """

    target_miou: float = 0.0

    RANGES: ClassVar[dict] = {"target_miou": "[0, 1]"}

    def __post_init__(self) -> None:
        check_params(self)


def _walk(entry: Path, seen: dict) -> None:
    """Collect ``entry`` and every entry upstream of it (by folder) into ``seen``."""
    from pipeline import load_manifest, upstream_entries

    if entry in seen:
        return
    seen[entry] = load_manifest(entry)
    for up in upstream_entries(entry).values():
        for e in (up.values() if isinstance(up, dict) else [up]):
            _walk(Path(e), seen)


def _chain(entry: Path, root: Path) -> dict:
    """{stage: entry folder relative to the cache root} of everything that fed ``entry``."""
    from pipeline import load_manifest, upstream_entries

    chain: dict = {}
    stack = [entry]
    while stack:
        e = stack.pop()
        chain.setdefault(load_manifest(e)["stage"], str(e.relative_to(root)))
        for up in upstream_entries(e).values():
            stack += [Path(x) for x in (up.values() if isinstance(up, dict) else [up])]
    return chain


def _write_csv(path: Path, rows: list[dict]) -> None:
    keys: list[str] = []
    for r in rows:
        keys += [k for k in r if k not in keys and not isinstance(r[k], (dict, list))]
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.DictWriter(f, fieldnames=keys, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in keys})


def _run(ctx, inputs):
    from cobgs.evaluate.protocols import ORACLE_METHOD, aggregate, nanmean, oracle_choice
    from pipeline import entry_of, load_manifest

    p: SummaryParams = ctx.params
    scenes, seen = [], {}
    for item, path in sorted(inputs["scene"].items(), key=lambda kv: kv[0].id):
        t = read_json(Path(path) / Files.TRAIN)
        entry = entry_of(path)
        _walk(entry, seen)
        ev = t.get("eval") or {}
        extra = (load_manifest(entry).get("extra") or {})
        scenes.append({"scene": item["scene"], "psnr": ev.get("psnr"), "ssim": ev.get("ssim"),
                       "num_gaussians": t["num_gaussians"], "iterations": t["iterations"],
                       "train_views": len(t["train_views"]), "test_views": len(t["test_views"]),
                       "train_s": extra.get("train_s"), "s_per_it": extra.get("s_per_it"),
                       "entries": _chain(entry, entry.parents[2])})
    rows, heads = [], []
    for item, path in sorted(inputs["metrics"].items(), key=lambda kv: kv[0].id):
        row = dict(read_json(Path(path) / Files.METRICS)["row"])
        row["item"] = item.id
        entry = entry_of(path)
        _walk(entry, seen)
        heads.append((row, entry))
        rows.append(row)
        if row.get("warnings"):
            row["warning"] = " | ".join(row["warnings"])
    root = next(iter(seen)).parents[2] if seen else None
    for row, entry in heads:
        row["entries"] = _chain(entry, root)
    # FlashSplat at its best background bias per scene (an oracle chosen on the held-out GT,
    # docs/method.md §3), where the workflow sweeps the bias: copies of the chosen item's rows.
    oracle = oracle_choice(rows)
    for r in [r for r in rows if oracle.get(r["scene"]) == r["method"]]:
        rows.append(dict(r, method=ORACLE_METHOD, oracle_choice=r["method"], item=f"{r['item']}#oracle"))

    by_scene_method = aggregate(rows, METRICS, by=("scene", "method"), within="scene", over="object")
    by_method = aggregate(rows, METRICS, by=("method",), within="scene", over="object")
    for r in by_method:
        r["miou"] = r["iou"]
        if p.target_miou > 0:
            r["meets_target"] = bool(r["iou"] >= p.target_miou)

    timings = []
    for e, man in sorted(seen.items(), key=lambda kv: (kv[1]["stage"], kv[1]["item"]["id"])):
        timings.append({"stage": man["stage"], "item": man["item"]["id"] or "(workflow)",
                        "wall_s": man.get("wall_s"), "cpu_s": man.get("cpu_s"),
                        "hash_s": man.get("hash_s"), "peak_rss_bytes": man.get("peak_rss_bytes"),
                        "device": man.get("device"), "version": man.get("version"),
                        "entry": str(e.relative_to(root))})
    per_stage: dict = {}
    for t in timings:
        s = per_stage.setdefault(t["stage"], {"tasks": 0, "wall_s": 0.0, "cpu_s": 0.0})
        s["tasks"] += 1
        s["wall_s"] += t["wall_s"] or 0.0
        s["cpu_s"] += t["cpu_s"] or 0.0

    protocols = sorted({r["protocol"] for r in rows})
    warnings = [{"item": r["item"], "message": m} for r in rows for m in r.get("warnings") or []]
    if warnings:
        ctx.warn(f"{len(warnings)} result(s) with a warning: " + ", ".join(w["item"] for w in warnings[:5])
                 + (" ..." if len(warnings) > 5 else "") + " (summary.json 'warnings')")
    out = {"format": "cobgs-summary", "version": 1, "scenes": scenes, "protocols": protocols, "rows": rows, "by_scene_method": by_scene_method, "by_method": by_method,
           "oracle_choice": oracle, "stage_totals": per_stage, "timings": timings, "cache_root": str(root) if root else None,
           "overall": {"miou": nanmean(r["iou"] for r in by_method), "target_miou": p.target_miou or None},
           "warnings": warnings}
    write_json(ctx.out_dir / Files.SUMMARY, out)
    _write_csv(ctx.out_dir / Files.SUMMARY_CSV, rows)
    _write_csv(ctx.out_dir / Files.BY_METHOD, by_method)
    _write_csv(ctx.out_dir / Files.BY_SCENE_METHOD, by_scene_method)
    _write_csv(ctx.out_dir / Files.TIMINGS, timings)
    _write_csv(ctx.out_dir / Files.SCENES, scenes)
    for r in by_method:
        ctx.log.info("%-14s mIoU %.4f  mBIoU %.4f  mAcc %.4f  PSNR %.2f (vanilla %.2f) dB  [%d scenes, %d objects]",
                     r["method"], r["iou"], r["biou"], r["acc"], r["psnr"], r["psnr_vanilla"], r["scenes"],
                     r["objects"])
    ctx.note(by_method={r["method"]: {"miou": r["iou"], "mbiou": r["biou"], "psnr": r["psnr"]} for r in by_method},
             rows=len(rows))
    return {"summary": ctx.out_dir}


STAGE = Stage(
    name="summary", version=4, run=_run, inputs=("metrics", "scene"), outputs=("summary",), params=SummaryParams,
    level=(), resources=Resources(cpus=1),
    description="JSON/CSV summary over every scene x method x object, with per-stage timings",
)
