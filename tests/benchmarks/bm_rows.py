"""Row means and paired differences straight from a workflow cache's evaluate entries, for a
partial `make bench` (a few scenes and rows run with ``--items``), where the report's tables,
which want whole scenes, are not drawn yet.

Run (not collected by pytest)::

    .venv/bin/python tests/benchmarks/bm_rows.py --cache runs/cache \\
        [--workflow workflows/synthetic_bench.toml] [--route "dataset masks + noise"] \\
        --rows ours,raem_paper,ngs,ngs_checked \\
        --pair ours:ngs --pair ngs_checked:ours \\
        --pair forward_coarse_fast/ours:forward_coarse/ours --train
    .venv/bin/python tests/benchmarks/bm_rows.py --cache runs/cache --route "dataset masks" \\
        --versus ours_per_use --rows cobgs,ngs --best-of sa3d,flashsplat,sa3d_strict
    .venv/bin/python tests/benchmarks/bm_rows.py --cache runs/cache --workflow workflows/demo.toml \\
        --baseline-set train.recipe=3dgs --train --pair demo/cobgs:demo@baseline/cobgs

The entries read are the workflow's current ones (``pipeline.entries``: the keys its tasks have
now), so an entry that a changed upstream made stale (a scene retrained on another SfM) is not
mixed in. ``--train`` adds, per scene, its training: recipe, iterations, Gaussians, held-out
PSNR, CPU time and the SfM entry it read (the first 12 hex digits of the sfm task's key: equal
for scenes that share one).

Per scene: each row's mean over the objects it has (headline mBIoU, occlusion-aware mBIoU,
released mBIoU, mIoU), then each ``--pair A:B``: mean(A − B) with the report's bootstrap over
views (``cobgs.evaluate.protocols.bootstrap_mean_diff``, objects weighted equally), on the views
and objects both have. ``A`` / ``B`` are rows (methods) of one scene, or ``scene/row`` to pair
across scenes (a scene trained with another recipe: the same views and GT masks).
``--baseline-set`` reads the same workflow a second time under other ``--set`` values (its scenes
named ``<scene>@baseline``), to pair a workflow against itself with one param changed.

``--boundary`` adds, per scene and object (issue 57: what COB-GS's boundaries depend on, on the
trained scene before any refinement; :mod:`cobgs.evaluate.boundary`): the Gaussians whose
3-sigma footprint crosses the object's mask boundary in a training view (count, median
footprint radius, world size and opacity), and the held-out renders' PSNR in a 3-pixel band
around the object's visible mask edge beside the whole image's.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

METRICS = {"biou": "per_view", "biou_occlusion": "per_view_occlusion", "biou_released": "per_view_released"}
LABELS = {"biou": "headline mBIoU", "biou_occlusion": "occlusion-aware mBIoU", "biou_released": "released mBIoU",
          "iou": "mIoU"}


def load(workflow: Path, cache: Path, sets=(), route: str = "") -> tuple[dict, dict]:
    """``(rows, trainings)``: (scene, method, object) -> the done evaluate entry's metrics.json,
    and scene -> its done training's facts, for the tasks ``workflow`` has now; with ``route``,
    only the objects whose masks came that way (the row's ``mask_route``, as the report's
    Masks column: "dataset masks", "dataset masks + noise", ...)."""
    from pipeline import entries, load_workflow
    from reports.collect import DESCRIPTORS, read_artifact_json
    from stages.registry import load_registry

    wf = load_workflow(workflow, load_registry(), list(sets))
    rows, trainings = {}, {}
    for rec in entries(wf, cache):
        if rec.state != "done":
            continue
        if rec.stage == "evaluate":
            m = read_artifact_json(rec.output("metrics"), DESCRIPTORS["metrics"], rec.task.id)
            v = rec.item.values  # (not the row's names: a shared dataset entry names its twin's scene)
            if {"scene", "method", "object"} <= set(v) and (not route or m["row"].get("mask_route") == route):
                rows[(v["scene"], v["method"], v["object"])] = m
        elif rec.stage == "train":
            t = read_artifact_json(rec.output("scene"), DESCRIPTORS["scene"], rec.task.id)
            man = rec.manifest
            trainings[rec.item.id] = {
                "recipe": (t.get("config") or {}).get("recipe") or "3dgs",
                "iterations": t.get("iterations"), "gaussians": t.get("num_gaussians"),
                "psnr": (t.get("eval") or {}).get("psnr"), "cpu_s": man.get("cpu_s"),
                "wall_s": man.get("wall_s"), "sfm": (man.get("inputs", {}).get("poses") or {}).get("key", "")[:12]}
    return rows, trainings


def boundary_rows(workflow: Path, cache: Path, sets=(), scenes=(), band_px: int = 3) -> list[dict]:
    """Per scene (of ``scenes``, all when empty) x object with masks: the boundary measures of the
    scene's trained baseline (module docstring)."""
    import numpy as np

    from cobgs.configs import Files
    from cobgs.evaluate.boundary import band_psnr, edge_band, straddling_gaussians
    from cobgs.gaussians.ply import load_ply
    from pipeline import entries, load_workflow
    from stages._common import load_scene, read_mask_png
    from stages.registry import load_registry

    wf = load_workflow(workflow, load_registry(), list(sets))
    done: dict = {}
    for rec in entries(wf, cache):
        if rec.state == "done" and rec.stage in ("dataset", "sfm", "train", "masks"):
            done[(rec.stage, rec.item.id)] = rec
    out = []
    for (stage, sid), rec in sorted(done.items()):
        if stage != "train" or (scenes and sid not in scenes) or ("dataset", sid) not in done:
            continue
        poses = done[("sfm", sid)].output("poses") if ("sfm", sid) in done else None
        scene = load_scene(done[("dataset", sid)].output("dataset"), poses)
        model = load_ply(rec.output("scene") / Files.SCENE_PLY)
        renders = rec.output("scene") / Files.RENDERS
        for (st, oid), mrec in sorted(done.items()):
            if st != "masks" or not oid.startswith(sid + "/"):
                continue
            obj = oid.split("/", 1)[1]
            folder = mrec.output("masks")
            masks = [read_mask_png(folder / f"{v.name}.png", v.width, v.height).numpy()
                     if (folder / f"{v.name}.png").is_file() else None for v in scene.train]
            st_ = straddling_gaussians(model, [v.camera for v in scene.train], masks)
            name = (mrec.item.attrs.get("object") and getattr(mrec.item.attrs["object"], "mask", "")) or obj
            band, whole = [], []
            for v in scene.test:
                gt = v.masks.get(name)
                f = renders / f"{v.name}.png"
                if gt is None or not f.is_file():
                    continue
                import cv2

                render = cv2.imread(str(f), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)[:, :, ::-1]
                ref = (v.image.clamp(0, 1).numpy() * 255.0).round().astype(np.uint8)
                b = edge_band(gt.numpy(), band_px)
                if b.any():
                    band.append(band_psnr(render, ref, b))
                    whole.append(band_psnr(render, ref))
            out.append({"scene": sid, "object": obj, "gaussians": st_["gaussians"], "straddling": st_["straddling"],
                        "radius_px": st_["radius_px_median"], "scale": st_["scale_median"],
                        "opacity": st_["opacity_median"], "band_psnr": float(np.mean(band)) if band else float("nan"),
                        "psnr": float(np.mean(whole)) if whole else float("nan"), "views": len(band)})
    return out


def _side(spec: str, scene: str) -> tuple[str, str]:
    return tuple(spec.split("/", 1)) if "/" in spec else (scene, spec)


def pair_diff(R: dict, a: tuple[str, str], b: tuple[str, str], metric: str):
    from cobgs.evaluate.protocols import bootstrap_mean_diff

    pairs = {}
    objects = sorted({o for (s, m, o) in R if (s, m) == a} & {o for (s, m, o) in R if (s, m) == b})
    for o in objects:
        pa = R[(a[0], a[1], o)]["details"][METRICS[metric]]
        pb = R[(b[0], b[1], o)]["details"][METRICS[metric]]
        pairs[o] = [(pa[v]["biou"], pb[v]["biou"]) for v in pa if v in pb]
    return bootstrap_mean_diff(pairs) if pairs else None


def _mean(R: dict, scene: str, row: str, metric: str):
    ms = [R[k]["row"][metric] for k in R if k[:2] == (scene, row)]
    return (100 * statistics.mean(ms), len(ms)) if ms else (None, 0)


def versus_tables(R: dict, scenes: list, ref: str, rows: list, best_of: list) -> str:
    """Per protocol, a Markdown table: a line per scene, ``ref``'s mean, then per row (and the
    best of ``best_of`` by headline mean, named) its mean and ``ref`` − it with the interval."""
    out = []
    for metric in ("biou", "biou_occlusion"):
        cols = rows + (["best peer"] if best_of else [])
        out += [f"\n{LABELS[metric]} (mean over objects; {ref} − row, 95 % interval over views)\n",
                f"| scene | {ref} | " + " | ".join(cols) + " |", "|---" * (len(cols) + 2) + "|"]
        for s in scenes:
            m, n = _mean(R, s, ref, metric)
            if m is None:
                continue
            cells = [f"{s} ({n})", f"{m:.2f}"]
            picks = list(rows)
            if best_of:
                have = [(h, r) for r in best_of if (h := _mean(R, s, r, "biou")[0]) is not None]
                picks.append(max(have)[1] if have else "")
            for i, r in enumerate(picks):
                v, _ = _mean(R, s, r, metric) if r else (None, 0)
                if v is None:
                    cells.append("")
                    continue
                d = pair_diff(R, (s, ref), (s, r), metric)
                name = f"{r}: " if i >= len(rows) else ""
                cells.append(f"{name}{v:.2f}" + (f", {d['diff']:+.2f} [{d['lo']:+.2f}, {d['hi']:+.2f}]" if d else ""))
            out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cache", type=Path, required=True)
    ap.add_argument("--workflow", type=Path, default=Path(__file__).resolve().parents[2] / "workflows" / "synthetic_bench.toml")
    ap.add_argument("--set", action="append", default=[], metavar="K=V", help="as cobgs run --set")
    ap.add_argument("--train", action="store_true", help="each scene's training (recipe, Gaussians, PSNR, SfM entry)")
    ap.add_argument("--boundary", action="store_true",
                    help="per scene and object: the Gaussians straddling the mask boundary and the held-out PSNR "
                         "in a 3-pixel band around the mask edge (issue 57; cobgs.evaluate.boundary)")
    ap.add_argument("--rows", default="", help="methods to tabulate, comma-separated (default: all)")
    ap.add_argument("--scenes", default="", help="scenes, comma-separated (default: all in the cache)")
    ap.add_argument("--pair", action="append", default=[], metavar="A:B")
    ap.add_argument("--baseline-set", action="append", default=[], metavar="K=V",
                    help="also read the workflow's entries under these --set values, as scene "
                         "'<scene>@baseline' (pair with --pair demo/cobgs:demo@baseline/cobgs)")
    ap.add_argument("--route", default="", help='only objects with this mask route ("dataset masks", '
                    '"dataset masks + noise"; default: every route, which mixes them in a row\'s mean)')
    ap.add_argument("--versus", default="", metavar="REF",
                    help="instead of the per-scene lists: one table per protocol, a line per scene, REF's "
                         "mean and each of --rows as its mean and REF minus it [interval]")
    ap.add_argument("--best-of", default="", metavar="ROWS",
                    help="with --versus: one more column, per scene the row among these with the highest "
                         "headline mean (the best peer), named")
    args = ap.parse_args(argv)
    bad = [spec for spec in args.pair if spec.count(":") != 1 or "" in spec.split(":")]
    if bad:
        ap.error(f"--pair takes A:B (rows, or scene/row), got {bad[0]!r}")
    if args.boundary:
        rows = boundary_rows(args.workflow, args.cache, args.set, [s for s in args.scenes.split(",") if s])
        print("| scene | object | Gaussians | straddling | median footprint px | median size | median opacity | "
              "band PSNR (3 px) | whole PSNR | views |")
        print("|---|---|---|---|---|---|---|---|---|---|")
        for r in rows:
            print(f"| {r['scene']} | {r['object']} | {r['gaussians']:,} | {r['straddling']:,} | {r['radius_px']:.1f} | "
                  f"{r['scale']:.4f} | {r['opacity']:.2f} | {r['band_psnr']:.2f} | {r['psnr']:.2f} | {r['views']} |")
        if not args.train and not args.pair and not args.versus:
            return 0
    R, T = load(args.workflow, args.cache, args.set, args.route)
    if args.baseline_set:
        RB, TB = load(args.workflow, args.cache, args.baseline_set, args.route)
        R.update({(f"{s}@baseline", m, o): v for (s, m, o), v in RB.items()})
        T.update({f"{s}@baseline": v for s, v in TB.items()})
    if not R:
        raise SystemExit(f"{args.cache}: no done evaluate entries of {args.workflow} with a row"
                         + (f" and mask route {args.route!r}" if args.route else ""))
    scenes = [s for s in args.scenes.split(",") if s] or sorted({k[0] for k in R})
    rows = [r for r in args.rows.split(",") if r] or sorted({k[1] for k in R})
    if args.versus:
        print(versus_tables(R, scenes, args.versus, [r for r in rows if r != args.versus],
                            [r for r in args.best_of.split(",") if r]))
        return 0
    if args.train:
        print("| scene | recipe | iterations | Gaussians | held-out PSNR | train CPU s | SfM entry |")
        print("|---|---|---|---|---|---|---|")
        for s in scenes:
            t = T.get(s)
            if t is not None:
                print(f"| {s} | {t['recipe']} | {t['iterations']} | {t['gaussians']:,} | {t['psnr']:.2f} | "
                      f"{t['cpu_s']:.0f} | {t['sfm']} |")
    for s in scenes:
        have = [r for r in rows if any(k[:2] == (s, r) for k in R)]
        if not have:
            continue
        print(f"\n### {s}\n")
        print("| row (objects) | " + " | ".join(LABELS[m] for m in ("biou", "biou_occlusion", "biou_released", "iou"))
              + " |")
        print("|---|---|---|---|---|")
        for r in have:
            means = [_mean(R, s, r, m) for m in ("biou", "biou_occlusion", "biou_released", "iou")]
            print(f"| {r} ({means[0][1]}) | " + " | ".join(f"{v:.2f}" for v, _ in means) + " |")
        lines = []
        for spec in args.pair:
            left, right = spec.split(":", 1)
            a, b = _side(left, s), _side(right, s)
            if a[0] != s:  # a pair is listed under its left side's scene
                continue
            for metric in ("biou", "biou_occlusion"):
                d = pair_diff(R, a, b, metric)
                if d is not None:
                    lines.append(f"- {'/'.join(a)} − {'/'.join(b)}, {LABELS[metric]}: {d['diff']:+.2f} "
                                 f"[{d['lo']:+.2f}, {d['hi']:+.2f}] ({d['objects']} objects)")
        if lines:
            print()
            print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
