"""The object-render check's keep rule, measured on refinements a workflow's cache already holds
(issue 59 item 2; ``RefineConfig.object_check_rule``; :mod:`cobgs.refine.consistency`).

The check runs after the refinement and reads nothing the refinement's own steps depend on, so
one refined scene serves every rule: for each done refine entry of ``--row`` (a row that runs
the check, ``object_check = "per_use"`` or ``"visible"``) this script

1. takes the foreground before the check (the labels' verdict, label > 0.9, from the stored logits) and the
   row's own masks (the masks entry the refinement read);
2. runs :func:`cobgs.refine.consistency.object_render_check` with each rule, with the λ and
   edge band the refinement ran with, and checks that the row's own rule gives back the stored
   foreground exactly (else it stops: the entry is not what this script would compute);
3. renders each rule's object alone in the held-out views as the segment stage does (the
   foreground with its label values, above 0.5) and scores it as the evaluate stage scores the
   headline (``cobgs.evaluate.protocols.exact_scores`` against the amodal GT where the dataset
   has one).

It prints, per scene and mask route, each rule's mean headline mBIoU and the paired difference
(``bootstrap_mean_diff``: objects weighted equally, views resampled), then per ``--group`` (several
baselines of one scene) the difference pooled over baselines (``bootstrap_across_baselines``).
``--versus ROWS`` pairs the last rule with other rows' own evaluate entries (their headline
per view), on each scene and pooled the same way.

Run (not collected by pytest)::

    .venv/bin/python tests/benchmarks/bm_check_rule.py WORKFLOW --cache CACHE --row ours_per_use \\
        [--scenes forward_coarse,orbit_coarse] [--rules votes,iou] [--json out.json] \\
        [--group forward_coarse=forward_coarse,forward_coarse_s1t0,...] [--versus raem_paper,flashsplat]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))


def _entries(workflow: Path, cache: Path, row: str, scenes: set, sets=(), versus=()):
    """{(scene, object): {"refined", "masks", "route", "versus": {row: per-view headline}}} and
    {scene: (dataset, poses)}."""
    from pipeline import entries, load_workflow
    from reports.collect import DESCRIPTORS, read_artifact_json
    from stages.registry import load_registry

    wf = load_workflow(workflow, load_registry(), list(sets))
    objs, data, masks, route, other = {}, {}, {}, {}, {}
    for rec in entries(wf, cache):
        if rec.state != "done":
            continue
        v = rec.item.values
        s = v.get("scene")
        if scenes and s not in scenes:
            continue
        if rec.stage == "refine" and v.get("method") == row:
            objs[(s, v["object"])] = Path(rec.output("refined"))
        elif rec.stage == "masks":
            masks[(s, v["object"])] = Path(rec.output("masks"))
        elif rec.stage == "evaluate" and v.get("method") in (row, *versus):
            m = read_artifact_json(rec.output("metrics"), DESCRIPTORS["metrics"], rec.task.id)
            if v["method"] == row:
                route[(s, v["object"])] = m["row"].get("mask_route", "")
            else:
                other.setdefault((s, v["object"]), {})[v["method"]] = {
                    n: x["biou"] for n, x in m["details"]["per_view"].items()}
        elif rec.stage == "dataset":
            data.setdefault(s, {})["dataset"] = Path(rec.output("dataset"))
        elif rec.stage == "sfm":
            data.setdefault(s, {})["poses"] = Path(rec.output("poses"))
    out = {k: {"refined": p, "masks": masks.get(k), "route": route.get(k, ""), "versus": other.get(k, {})}
           for k, p in objs.items()}
    return out, data


def measure(key, entry, data, rules) -> dict:
    """Per rule: removed count and the held-out views' headline BIoU (one object)."""
    import dataclasses

    import torch

    from cobgs.configs import CHECKED, LABEL
    from cobgs.evaluate import protocols as E
    from cobgs.refine.alternation import label_sets
    from cobgs.refine.consistency import object_render_check
    from cobgs.refine.scores import pixel_labels_from_mask
    from cobgs.refine.segment import render_object_mask
    from stages._common import Files, load_scene, masks_for_views, read_json, read_spec
    from stages.evaluate import _amodal_gts
    from stages.segment import read_refined

    scene_name, obj = key
    d = entry["refined"]
    ref = read_json(d / Files.REFINE)
    config = ref.get("config") or {}
    stored_rule = config.get("object_check_rule", "votes")
    if config.get("object_check", "off") not in CHECKED:
        raise SystemExit(f"{scene_name}/{obj}: the row's refinement ran no object check")
    result, in_scene, seg = read_refined(d, "cpu")
    model, stored = result.model, result.foreground
    # the labels' verdict (label > 0.9), as refine() computes it before the check; the in-scene
    # set may hold more since in_scene_undecided = "votes"
    before = label_sets(model.data[LABEL])[0]
    dataset, poses = data[scene_name]["dataset"], data[scene_name]["poses"]
    scene = load_scene(dataset, poses)
    masks = masks_for_views(entry["masks"], scene.train)
    views = [v for v, m in zip(scene.train, masks) if m is not None]
    labels = [pixel_labels_from_mask(m, v.height, v.width) for v, m in zip(scene.train, masks) if m is not None]
    spec = read_spec(dataset)
    gt_name = ref.get("dataset_object") or ref.get("object") or obj
    test = {v.name: v for v in scene.test}
    visible = {n: (v.masks[gt_name].cpu().numpy() if gt_name in v.masks else None) for n, v in test.items()}
    amodal = _amodal_gts(spec, dataset, gt_name, visible)
    gts = amodal if amodal is not None else visible
    out = {}
    for rule in rules:
        kept = object_render_check(model, before, views, labels, float(config.get("mask_lambda", 1.0)),
                                   edge_px=int(config.get("object_check_edge_px", 0)), rule=rule)
        if rule == stored_rule and not torch.equal(kept, stored):
            raise SystemExit(f"{scene_name}/{obj}: rule {rule!r} does not give back the stored foreground "
                             f"({int(stored.sum())} against {int(kept.sum())} Gaussians)")
        alone = dataclasses.replace(result, foreground=kept)  # rendered as the segment stage renders it
        preds = {n: render_object_mask(alone, v.camera).numpy() for n, v in test.items()}
        s = E.exact_scores(preds, gts)
        out[rule] = {"removed": int((before & ~kept).sum()), "foreground": int(kept.sum()),
                     "biou": s["biou"], "per_view": {n: p["biou"] for n, p in s["per_view"].items()}}
    out["before"] = int(before.sum())
    out["route"] = entry["route"]
    out["versus"] = entry["versus"]
    return out


def pairs_of(results: dict, keys, a: str, b: str) -> dict:
    """object -> [(a, b) per held-out view]; ``b`` a rule, or ``"row:NAME"`` (another row's entry)."""
    def values(k, x):
        return results[k]["versus"].get(x[4:], {}) if x.startswith("row:") else results[k][x]["per_view"]

    out = {}
    for k in keys:
        va, vb = values(k, a), values(k, b)
        if va and vb:
            out[k[1]] = [(va[n], vb[n]) for n in va if n in vb]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("workflow", type=Path)
    ap.add_argument("--cache", type=Path, required=True)
    ap.add_argument("--row", required=True, help="a row that runs the object check")
    ap.add_argument("--scenes", default="", help="comma list (default: every scene with the row)")
    ap.add_argument("--rules", default="votes,iou")
    ap.add_argument("--set", dest="sets", action="append", default=[], help="workflow overrides (as cobgs run)")
    ap.add_argument("--group", action="append", default=[],
                    help="NAME=scene,scene,...: baselines of one scene, pooled (repeatable)")
    ap.add_argument("--versus", default="", help="comma list of rows to pair the last rule with")
    ap.add_argument("--json", type=Path, help="write every object's result here")
    a = ap.parse_args(argv)
    from cobgs.evaluate.protocols import bootstrap_mean_diff

    rules = [r for r in a.rules.split(",") if r]
    scenes = {s for s in a.scenes.split(",") if s}
    versus = [r for r in a.versus.split(",") if r]
    todo, data = _entries(a.workflow, a.cache, a.row, scenes, a.sets, versus)
    results = {}
    for k in sorted(todo):
        results[k] = measure(k, todo[k], data, rules)
        r = results[k]
        print(f"{k[0]:22s} {k[1]:14s} foreground {r['before']:6d}  "
              + "  ".join(f"{x}: -{r[x]['removed']:<4d} {100 * r[x]['biou']:6.2f}" for x in rules), flush=True)
    if a.json:
        a.json.write_text(json.dumps({f"{s}/{o}": v for (s, o), v in results.items()}, indent=1))
    base, other = rules[0], rules[1:]
    print("\n| scene | masks | objects | " + " | ".join(f"{x} headline mBIoU" for x in rules)
          + " | " + " | ".join(f"{x} − {base} [95 %]" for x in other) + " |")
    print("|---|---|---|" + "---|" * (len(rules) + len(other)))
    routes = sorted({r["route"] for r in results.values()})
    by = {}
    for s in sorted({k[0] for k in results}):
        for route in routes:
            keys = [k for k in results if k[0] == s and results[k]["route"] == route]
            if not keys:
                continue
            by[(s, route)] = keys
            means = [statistics.fmean(100 * results[k][x]["biou"] for k in keys) for x in rules]
            diffs = []
            for x in other:
                d = bootstrap_mean_diff(pairs_of(results, keys, x, base))
                diffs.append(f"{d['diff']:+.2f} [{d['lo']:+.2f}, {d['hi']:+.2f}]")
            print(f"| {s} | {route} | {len(keys)} | " + " | ".join(f"{m:.2f}" for m in means) + " | "
                  + " | ".join(diffs) + " |")
    last = rules[-1]
    comparisons = [(x, base) for x in other] + [(last, f"row:{r}") for r in versus]
    if versus:
        print("\n| scene | masks | " + " | ".join(f"{last} − {r} [95 %]" for r in versus) + " |")
        print("|---|---|" + "---|" * len(versus))
        for (s, route), keys in by.items():
            cells = []
            for r in versus:
                d = bootstrap_mean_diff(pairs_of(results, keys, last, f"row:{r}"))
                cells.append("-" if d is None else f"{d['diff']:+.2f} [{d['lo']:+.2f}, {d['hi']:+.2f}] ({d['objects']})")
            print(f"| {s} | {route} | " + " | ".join(cells) + " |")
    for g in a.group:
        name, members = g.split("=", 1)
        members = [m for m in members.split(",") if m]
        for route in routes:
            for x, y in comparisons:
                pooled = {m: pairs_of(results, by[(m, route)], x, y) for m in members if (m, route) in by}
                print_pooled(f"{name} | {route} | {x} − {y.replace('row:', '')}", pooled)
    return 0


def print_pooled(what: str, pooled: dict) -> None:
    """One line: the difference pooled over baselines (``bootstrap_across_baselines`` of
    {baseline: {object: [(x, y) per view]}}) with each baseline's own; nothing when empty."""
    from cobgs.evaluate.protocols import bootstrap_across_baselines

    d = bootstrap_across_baselines(pooled)
    if d is None:
        return
    per = ", ".join(f"{b}: {v:+.2f}" for b, v in d["per_baseline"].items())
    print(f"pooled {what}: {d['diff']:+.2f} [{d['lo']:+.2f}, {d['hi']:+.2f}] ({d['baselines']} baselines; {per})")


if __name__ == "__main__":
    raise SystemExit(main())
