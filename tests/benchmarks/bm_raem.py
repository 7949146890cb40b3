"""RAEM's pruning, measured on refinements a workflow's cache already holds (issue 59 item 2).

RAEM is the refinement's last edit: it removes Gaussians and changes no label
(:func:`cobgs.refine.alternation.apply_raem`). So one refinement made with ``raem = "off"``
(the ``no_raem`` row: BAGS + BGTR) serves every pruning rule. For each done refine entry of
``--row`` this script

1. reads the refined scene, its last mask stage's scores and the masks it was refined with;
2. applies each rule, then the default's two outputs as the refine stage makes them
   (:func:`cobgs.refine.alternation.final_sets` with the default's check and in-scene options:
   the object-render check for the object alone; the labels' verdict plus the undecided
   Gaussians the votes call object for the object within the scene);
3. renders both as the segment stage does and scores them as the evaluate stage does: the
   headline protocol (object alone against its whole silhouette where the dataset has one) and
   the occlusion-aware one (the object within the scene against its visible mask).

Rules:

* ``off``: nothing removed;
* ``paper``: RAEM as the paper describes it (tiny ambiguous Gaussians; the default's);
* ``spare``: ``paper``, except that a Gaussian the labels call object (label > 0.9) is never
  pruned; the check (IoU rule) judges those with the masks' evidence instead
  (``RefineConfig.raem_spare_object``, off by default).
* ``object_set`` (``RefineConfig.raem_object_by_masks``, off by default): per object, ``spare`` where the
  object alone, drawn above 0.5, agrees better with the training masks than under ``paper`` (the
  intersection over union over every training view's judged pixels, the pixels where something
  else hides the object in the scene left out, as the check leaves them out), else ``paper``:
  the object's own pruned Gaussians go back only on the masks' evidence.

With ``--check-row ROW`` (a row that runs ``paper`` with the default's check, e.g.
``ours_per_use``) it first checks that ``paper`` gives back ROW's stored object and in-scene sets
exactly, object by object (a refinement made with the same splits: not forward_coarse, where
the default's object-share split differs from ``no_raem``'s), and says so.

Prints per object each rule's scores and pruned count, then per scene and mask route the paired
differences to ``paper`` (objects weighted equally, views resampled).

Run (not collected by pytest)::

    .venv/bin/python tests/benchmarks/bm_raem.py workflows/synthetic_bench.toml --cache CACHE \\
        [--row no_raem] [--scenes orbit_dense,...] [--objects pole,pole_noisy] [--check-row ours_per_use]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

RULES = ("off", "paper", "spare", "object_set")
#: The refine options that decide the outputs after RAEM (cobgs.refine.alternation.final_sets):
#: the default's are applied to every rule
OUTPUT_OPTIONS = ("object_check", "object_check_rule", "object_check_edge_px", "in_scene_undecided")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("workflow", type=Path)
    ap.add_argument("--cache", type=Path, required=True)
    ap.add_argument("--row", default="no_raem")
    ap.add_argument("--scenes", default="")
    ap.add_argument("--objects", default="")
    ap.add_argument("--check-row", default="")
    ap.add_argument("--set", action="append", default=[], metavar="K=V", help="as cobgs run --set")
    ap.add_argument("--json", type=Path, help="also write every object's per-view scores here")
    a = ap.parse_args(argv)

    import dataclasses

    import numpy as np
    import torch

    from bm_check_rule import _entries
    from cobgs.configs import LABEL, RefineConfig
    from cobgs.evaluate import protocols as E
    from cobgs.refine.alternation import apply_raem, final_sets, label_sets
    from cobgs.refine.consistency import drawn_agreement
    from cobgs.refine.scores import pixel_labels_from_mask
    from cobgs.refine.segment import render_object_mask, visible_object_mask
    from pipeline import entries, load_workflow
    from stages._common import Files, load_scene, masks_for_views, read_json, read_spec
    from stages.evaluate import _amodal_gts
    from stages.registry import load_registry
    from stages.segment import read_refined

    objects = {o for o in a.objects.split(",") if o}
    scenes = {s for s in a.scenes.split(",") if s}
    todo, data = _entries(a.workflow, a.cache, a.row, scenes, a.set)
    stored = {}  # (scene, object) -> the check row's refine output folder
    if a.check_row:
        wf = load_workflow(a.workflow, load_registry(), list(a.set))
        for rec in entries(wf, a.cache):
            v = rec.item.values
            if rec.stage == "refine" and rec.state == "done" and v.get("method") == a.check_row:
                stored[(v["scene"], v["object"])] = Path(rec.output("refined"))
    default, fields = RefineConfig(), {f.name for f in dataclasses.fields(RefineConfig)}
    results = {}
    for (scene_name, obj), e in sorted(todo.items()):
        if objects and obj not in objects:
            continue
        d = e["refined"]
        ref = read_json(d / Files.REFINE)
        cfg = ref.get("config") or {}
        if cfg.get("raem") != "off":
            raise SystemExit(f"{scene_name}/{obj}: row {a.row!r} ran RAEM ({cfg.get('raem')!r}); it needs raem = 'off'")
        result, _, _ = read_refined(d, "cpu")
        scores = np.load(d / Files.STAGE_SCORES)
        last = torch.from_numpy(scores[f"stage_{len(scores.files) - 1}"])
        result = dataclasses.replace(result, config=cfg, stage_scores=[last])
        scene = load_scene(data[scene_name]["dataset"], data[scene_name]["poses"])
        masks = masks_for_views(e["masks"], scene.train)
        views = [v for v, m in zip(scene.train, masks) if m is not None]
        px = [pixel_labels_from_mask(m, v.height, v.width) for v, m in zip(scene.train, masks) if m is not None]
        # the refinement's own options (λ, labels, backend), with the default's check and in-scene set
        own = RefineConfig(**{k: v for k, v in cfg.items() if k in fields})
        outputs = dataclasses.replace(own, **{k: getattr(default, k) for k in OUTPUT_OPTIONS})
        gt_name = ref.get("dataset_object") or ref.get("object") or obj
        test = {v.name: v for v in scene.test}
        visible = {n: (v.masks[gt_name].cpu().numpy() if gt_name in v.masks else None) for n, v in test.items()}
        amodal = _amodal_gts(read_spec(data[scene_name]["dataset"]), data[scene_name]["dataset"], gt_name, visible)
        headline_gt = amodal if amodal is not None else visible
        labels_fg = label_sets(result.model.data[LABEL])[0]
        out, agreement = {}, {}
        for rule in RULES:
            if rule == "object_set":  # spare only where the training masks say it draws the object better
                pick = "spare" if agreement["spare"] > agreement["paper"] else "paper"
                out[rule] = dict(out[pick], chose=pick)
                continue
            variant = "off" if rule == "off" else "paper"
            r = apply_raem(result, variant, scene.train, spare=labels_fg if rule == "spare" else None)
            kept, _, in_scene, _ = final_sets(r.model, views, px, outputs)
            agreement[rule] = drawn_agreement(r.model, kept, views, px)
            if rule == "paper" and (scene_name, obj) in stored:
                sdir = stored[(scene_name, obj)]
                _, s_in, s_seg = read_refined(sdir, "cpu")
                same = {"object alone": (len(s_seg["foreground"]) == len(kept)
                                         and np.array_equal(s_seg["foreground"], kept.numpy()))}
                if (read_json(sdir / Files.REFINE).get("config") or {}).get("in_scene_undecided") == "votes":
                    same["in the scene"] = same["object alone"] and np.array_equal(s_in.foreground.numpy(),
                                                                                   in_scene.numpy())
                print(f"{scene_name}/{obj}: 'paper' against {a.check_row}'s stored sets: " +
                      ", ".join(f"{k} {'identical' if v else 'DIFFERENT'}" for k, v in same.items()), flush=True)
            alone = dataclasses.replace(r, foreground=kept)
            within = dataclasses.replace(r, foreground=in_scene)
            head = E.exact_scores({n: render_object_mask(alone, v.camera).numpy() for n, v in test.items()},
                                  headline_gt)
            occl = E.exact_scores({n: visible_object_mask(within, v.camera).numpy() for n, v in test.items()},
                                  visible)
            out[rule] = {"pruned": 0 if r.raem_keep is None else int((~r.raem_keep).sum()), "object": int(kept.sum()),
                         "headline": {n: p["biou"] for n, p in head["per_view"].items()},
                         "occlusion": {n: p["biou"] for n, p in occl["per_view"].items()}}
        out["route"] = todo[(scene_name, obj)]["route"] or ref.get("mask_route", "")
        results[(scene_name, obj)] = out
        print(f"{scene_name:16s} {obj:14s} " + "  ".join(
            f"{k}: {100 * statistics.fmean(v['headline'].values()):6.2f} / "
            f"{100 * statistics.fmean(v['occlusion'].values()):6.2f} (pruned {v['pruned']}, object {v['object']}"
            + (f", {v['chose']}" if "chose" in v else "") + ")"
            for k, v in out.items() if k in RULES), flush=True)
    if a.json:
        a.json.write_text(json.dumps({f"{k[0]}/{k[1]}": v for k, v in results.items()}, indent=1))
    alts = [x for x in RULES if x != "paper"]
    print("\n| scene | masks | protocol | " + " | ".join(f"{x} − paper [95 %]" for x in alts) + " |\n|---|---|---|"
          + "---|" * len(alts))
    for s in sorted({k[0] for k in results}):
        for route in sorted({results[k]["route"] for k in results}):
            keys = [k for k in results if k[0] == s and results[k]["route"] == route]
            if not keys:
                continue
            for proto in ("headline", "occlusion"):
                cells = []
                for alt in alts:
                    pairs = {k[1]: [(results[k][alt][proto][n], results[k]["paper"][proto][n])
                                    for n in results[k]["paper"][proto]] for k in keys}
                    d = E.bootstrap_mean_diff(pairs)
                    cells.append(f"{d['diff']:+.2f} [{d['lo']:+.2f}, {d['hi']:+.2f}]")
                print(f"| {s} | {route} | {proto} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
