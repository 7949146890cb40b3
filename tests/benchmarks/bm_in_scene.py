"""Which Gaussians make the object within its scene (the occlusion-aware protocol's output),
measured on refinements a workflow's cache already holds (issue 59 item 2;
``RefineConfig.in_scene_undecided``).

Until 2026-11-29 the default rendered the object within its scene from the labels' verdict
(label > 0.9). A Gaussian split late, or judged on little evidence, can end the refinement
undecided (0.1 < label < 0.9): in neither set, although the mask loss's own closed form, the Σ α·T votes of the training masks in the scene render (object where object votes >
λ × background votes; :func:`cobgs.refine.consistency.label_votes`), has already decided it.
This script scores, for each done refine entry of ``--row`` (a ``per_use`` row):

* ``labels``: the labels' verdict (``in_scene_undecided = "labels"``, the default's output until
  2026-11-29);
* ``labels+undecided``: the same plus every undecided Gaussian whose votes say object (``"votes"``,
  the default since; the script checks that it gives back the stored set of such an entry);
* ``votes``: the closed form alone, for every Gaussian (FlashSplat's rule on this refined scene).

Each set is rendered within the scene as the segment stage renders ``pred_visible``
(:func:`cobgs.refine.segment.visible_object_mask`: the set's label values, 1 for the votes'
Gaussians that have no decided label, 0 elsewhere; above the bar) and scored
against the held-out views' visible masks as the evaluate stage does. Prints per object, then
per scene and mask route the paired differences to ``labels`` (objects weighted equally).

Run (not collected by pytest)::

    .venv/bin/python tests/benchmarks/bm_in_scene.py workflows/synthetic_bench.toml --cache CACHE \\
        --row ours_per_use [--scenes forward_coarse,orbit_coarse] [--group NAME=SCENE,SCENE,...] \\
        [--set refine.cobgs.in_scene_undecided=labels]
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parent))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("workflow", type=Path)
    ap.add_argument("--cache", type=Path, required=True)
    ap.add_argument("--row", required=True)
    ap.add_argument("--scenes", default="")
    ap.add_argument("--set", action="append", default=[], metavar="K=V",
                    help="as cobgs run --set (entries computed before a default changed: "
                         "--set refine.cobgs.in_scene_undecided=labels)")
    ap.add_argument("--group", action="append", default=[],
                    help="NAME=SCENE,SCENE,...: also the difference pooled over these baselines of one scene")
    a = ap.parse_args(argv)

    import dataclasses

    import torch

    from bm_check_rule import _entries, print_pooled
    from cobgs.evaluate import protocols as E
    from cobgs.configs import LABEL
    from cobgs.refine.alternation import BG_THRESHOLD, FG_THRESHOLD, label_sets
    from cobgs.refine.consistency import label_votes, object_by_votes, undecided_by_votes
    from cobgs.refine.scores import pixel_labels_from_mask
    from cobgs.refine.segment import visible_object_mask
    from stages._common import Files, load_scene, masks_for_views, read_json
    from stages.segment import read_refined

    todo, data = _entries(a.workflow, a.cache, a.row, {s for s in a.scenes.split(",") if s}, a.set)
    results = {}
    for (scene_name, obj), e in sorted(todo.items()):
        d = e["refined"]
        ref = read_json(d / Files.REFINE)
        lam = float((ref.get("config") or {}).get("mask_lambda", 1.0))
        _, in_scene, seg = read_refined(d, "cpu")
        if "foreground_in_scene" not in seg.files:
            raise SystemExit(f"{scene_name}/{obj}: row {a.row!r} keeps no in-scene set (object_check = 'per_use')")
        # the labels' verdict (label > 0.9) from the stored logits: the stored in-scene set holds
        # more where the entry was computed with in_scene_undecided = "votes"
        model, values = in_scene.model, in_scene.mask_values
        labels = label_sets(model.data[LABEL])[0]
        scene = load_scene(data[scene_name]["dataset"], data[scene_name]["poses"])
        masks = masks_for_views(e["masks"], scene.train)
        views = [v for v, m in zip(scene.train, masks) if m is not None]
        pixel = [pixel_labels_from_mask(m, v.height, v.width) for v, m in zip(scene.train, masks) if m is not None]
        w = label_votes(model, views, pixel, 2)
        votes = object_by_votes(w, lam)
        plus = labels | undecided_by_votes(values, w, lam, BG_THRESHOLD, FG_THRESHOLD)
        stored_rule = (ref.get("config") or {}).get("in_scene_undecided", "labels")
        expect = plus if stored_rule == "votes" else labels
        if not torch.equal(expect, in_scene.foreground):  # the entry is not what this script computes
            raise SystemExit(f"{scene_name}/{obj}: in_scene_undecided = {stored_rule!r} does not give back the "
                             f"stored in-scene set ({int(in_scene.foreground.sum())} against {int(expect.sum())})")
        ones = torch.where(labels, values, torch.ones_like(values))  # votes carry no label: value 1
        sets = {"labels": (labels, values), "labels+undecided": (plus, values),
                "votes": (votes, ones)}
        gt_name = ref.get("dataset_object") or ref.get("object") or obj
        test = {v.name: v for v in scene.test}
        gts = {n: (v.masks[gt_name].cpu().numpy() if gt_name in v.masks else None) for n, v in test.items()}
        out = {}
        for k, (s, vals) in sets.items():
            # rendered as the segment stage renders pred_visible
            shown = dataclasses.replace(in_scene, foreground=s, mask_values=vals)
            preds = {n: visible_object_mask(shown, v.camera).numpy() for n, v in test.items()}
            out[k] = {"added": int((s & ~labels).sum()), "removed": int((labels & ~s).sum()),
                      "per_view": {n: p["biou"] for n, p in E.exact_scores(preds, gts)["per_view"].items()}}
        results[(scene_name, obj)] = out
        print(f"{scene_name:16s} {obj:14s} " + "  ".join(
            f"{k}: {100 * statistics.fmean(v['per_view'].values()):6.2f} (+{v['added']}/-{v['removed']})"
            for k, v in out.items()), flush=True)
    print("\n| scene | masks | labels+undecided − labels [95 %] | votes − labels [95 %] |\n|---|---|---|---|")
    for s in sorted({k[0] for k in results}):
        for route in sorted({todo[k]["route"] for k in results}):
            keys = [k for k in results if k[0] == s and todo[k]["route"] == route]
            if not keys:
                continue
            cells = []
            for alt in ("labels+undecided", "votes"):
                pairs = {k[1]: [(results[k][alt]["per_view"][n], results[k]["labels"]["per_view"][n])
                                for n in results[k]["labels"]["per_view"]] for k in keys}
                d = E.bootstrap_mean_diff(pairs)
                cells.append(f"{d['diff']:+.2f} [{d['lo']:+.2f}, {d['hi']:+.2f}]")
            print(f"| {s} | {route} | " + " | ".join(cells) + " |")
    for g in a.group:
        name, members = g.split("=", 1)
        for route in sorted({todo[k]["route"] for k in results}):
            for alt in ("labels+undecided", "votes"):
                pooled = {}
                for m in (x for x in members.split(",") if x):
                    keys = [k for k in results if k[0] == m and todo[k]["route"] == route]
                    if keys:
                        pooled[m] = {k[1]: [(results[k][alt]["per_view"][n], results[k]["labels"]["per_view"][n])
                                            for n in results[k]["labels"]["per_view"]] for k in keys}
                print_pooled(f"{name} | {route} | {alt} − labels", pooled)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
