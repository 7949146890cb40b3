"""COB-GS through its alternation, stage by stage (issue 37: why it loses where it loses).

Run (not collected by pytest) on the benchmark's cache, after ``make bench`` trained the
scenes and made the masks::

    .venv/bin/python tests/benchmarks/bm_refine_trajectory.py --scene orbit_dense \\
        [--objects crate,ball] [--method raem_paper] [--set refine.cobgs.bgtr=false ...] \\
        [--out docs/benchmarks/data/trajectory]

For each object it reruns the refinement of that workflow row (the same config the refine
stage resolves) with a hook at the start and end of every stage and records, per stage:

* the headline protocol on the held-out views — the object-only render (label > 0.9,
  value 1, threshold 0.5) against the amodal GT: IoU, boundary IoU, and the wrong pixels
  split into false positives / false negatives, inside / outside the GT's boundary band
  (the band of the boundary IoU: width 2 % of the diagonal);
* Gaussians: count, split, pruned, foreground / undecided (0.1 < label < 0.9) / background,
  label changes (fg <-> not fg) since the previous stage;
* texture stages: how far the Gaussians move (means, in pixels of the first held-out
  camera at their depth) and how much their largest scale changes, for all Gaussians and
  for the children of the preceding split separately;
* the closed-form labels of the mask loss on the current geometry (per Gaussian, object if
  its Σ α·T over object pixels exceeds λ × that over background pixels: the limit the mask
  stages' label optimisation converges to) and their headline scores, to tell label error
  from geometry error.

Where the row has the object-render check (``refine.cobgs.object_check``), a last record
``kind = "check"`` scores the foreground after it (docs/method.md §7).

Writes ``<out>/<scene>__<method>__<object>.json`` and prints a table; ``cobgs report
WORKFLOW --trajectories OUT`` draws them in the report's refinement section (one figure per
scene of the run).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))


def _headline(model, fg, test, gts, band_ratio=0.02):
    """IoU / BIoU over the held-out views, and FP / FN pixels inside / outside the band."""
    from cobgs.evaluate import protocols as E
    from cobgs.evaluate.metrics import mask_boundary
    from cobgs.refine.result import RefineResult
    from cobgs.refine.segment import render_object_mask

    rr = RefineResult(method="cobgs", object_name="", model=model, foreground=fg, background=~fg,
                      mask_values=torch.ones(len(model)), mask_threshold=0.5)
    preds = {}
    fp_in = fp_out = fn_in = fn_out = 0
    for n, v in test.items():
        p = render_object_mask(rr, v.camera, threshold=0.5).cpu().numpy()
        preds[n] = p
        g = gts[n]
        if g is None or not g.any():
            continue
        band = mask_boundary(g, band_ratio) | mask_boundary(~g, band_ratio)
        fp, fn = p & ~g, ~p & g
        fp_in += int((fp & band).sum())
        fp_out += int((fp & ~band).sum())
        fn_in += int((fn & band).sum())
        fn_out += int((fn & ~band).sum())
    s = E.exact_scores(preds, gts)
    return {"iou": s["iou"], "biou": s["biou"], "fp_band": fp_in, "fp_far": fp_out, "fn_band": fn_in,
            "fn_far": fn_out}


def _closed_form(model, views, pixel_labels, lam):
    from cobgs.refine.peers import flashsplat_votes

    w = flashsplat_votes(model, views, pixel_labels, 2)
    return w[:, 1] > lam * w[:, 0], w.sum(1) > 0


def trajectory(wf, cache, scene_name, method, obj, sets_note=""):
    from cobgs.refine import alternation as R
    from cobgs.refine.scores import pixel_labels_from_mask
    from pipeline import entries
    from stages._common import load_scene, masks_for_views, read_json, read_spec
    from stages.evaluate import _amodal_gts
    from stages.refine import method_config
    from cobgs.gaussians.ply import load_ply
    from cobgs.train.adam_moments import MOMENTS_FILE, read_moments

    recs = {(r.stage, r.item.id): r for r in entries(wf, cache)}
    ds = recs[("dataset", scene_name)].output("dataset")
    spec = read_spec(ds)
    scene = load_scene(ds, recs[("sfm", scene_name)].output("poses"))
    sdir = recs[("train", scene_name)].output("scene")
    model = load_ply(sdir / "scene.ply")
    trained = read_json(sdir / "train.json")
    moments = read_moments(sdir / MOMENTS_FILE, len(model)) if (sdir / MOMENTS_FILE).is_file() else None
    mrec = recs[("masks", f"{scene_name}/{obj}")]
    masks = masks_for_views(mrec.output("masks"), scene.train)
    task = next(t for t in wf_plan(wf).tasks if t.stage.name == "refine" and t.item.id == f"{scene_name}/{method}/{obj}")
    config = method_config(task.params.value, spec.scene_type)
    dobj = read_json(mrec.output("masks") / "masks.json")["object"]
    test = {v.name: v for v in scene.test}
    vis = {n: (v.masks[dobj].cpu().numpy() if dobj in v.masks else None) for n, v in test.items()}
    gts = _amodal_gts(spec, ds, dobj, vis) or vis
    px = [pixel_labels_from_mask(m, v.height, v.width) for m, v in zip(masks, scene.train)]
    cam0 = next(iter(test.values())).camera

    rows: list[dict] = []
    state: dict = {}

    def labels(r):
        lg = r.model.data[config.label_name].detach()
        return torch.sigmoid(lg)

    def pixels(r, means):
        """Means in pixels of the first held-out camera (x, y) and their depth."""
        pc = means @ cam0.viewmat[:3, :3].T + cam0.viewmat[:3, 3]
        z = pc[:, 2].clamp_min(1e-6)
        return torch.stack([pc[:, 0] / z * cam0.fx, pc[:, 1] / z * cam0.fy], 1)

    def start(r, si, kind):
        state["means"] = r.model.means.detach().clone()
        state["smax"] = r.model.scales.detach().max(1).values.clone()
        state["n"] = len(r.model)

    def end(r, st):
        m = r.model
        lab = labels(r)
        fg = lab > R.FG_THRESHOLD
        row = {"stage": st.index, "kind": st.kind, "iteration": r.iteration, "gaussians": len(m),
               "split": st.split, "pruned": st.pruned, "ambiguous": st.ambiguous,
               "fg": int(fg.sum()), "undecided": int(((lab > R.BG_THRESHOLD) & ~fg).sum()),
               "bg": int((lab < R.BG_THRESHOLD).sum()), "mean_loss": st.mean_loss}
        row.update(_headline(m, fg, test, gts))
        cf, seen = _closed_form(m, scene.train, px, config.mask_lambda)
        cf = torch.where(seen, cf, fg)
        row["closed_form_flips"] = int((cf != fg).sum())
        h = _headline(m, cf, test, gts)
        row["cf_iou"], row["cf_biou"] = h["iou"], h["biou"]
        sc = r.last_mask_info.get("scores") if st.kind == "mask" else None
        if sc is not None and len(sc) == len(m):
            # the foreground without the Gaussians this stage found ambiguous (score < δ)
            for key, thr in (("unamb", config.threshold), ("unamb_half", config.threshold / 2)):
                h = _headline(m, fg & (sc >= thr), test, gts)
                row[f"{key}_iou"], row[f"{key}_biou"] = h["iou"], h["biou"]
        prev = state.get("fg")
        if prev is not None and len(prev) == len(fg):
            row["label_changes"] = int((prev != fg).sum())
        state["fg"] = fg.clone()
        if st.kind == "texture" and len(m) == state["n"]:
            d = (pixels(r, m.means.detach()) - pixels(r, state["means"])).norm(dim=1)
            ds_ = m.scales.detach().max(1).values / state["smax"]
            kids = state.get("children", 0)
            row["move_px_median"] = float(d.median())
            row["move_px_p95"] = float(d.quantile(0.95))
            row["scale_ratio_median"] = float(ds_.median())
            if kids:
                row["children_move_px_median"] = float(d[-kids:].median())
                row["children_scale_ratio_median"] = float(ds_[-kids:].median())
                row["children_fg"] = int(fg[-kids:].sum())
        if st.kind == "mask":
            state["children"] = 2 * st.split if config.split_children == 2 else st.split * config.split_children
        rows.append(row)
        print(f"  {st.kind:>7} {st.index:2d}: n {len(m):7d} split {st.split:5d} pruned {st.pruned:5d} "
              f"fg {row['fg']:6d} undecided {row['undecided']:5d}  IoU {100 * row['iou']:5.1f} BIoU "
              f"{100 * row['biou']:5.1f} (closed-form labels {100 * row['cf_biou']:5.1f})  FP band/far "
              f"{row['fp_band']}/{row['fp_far']} FN band/far {row['fn_band']}/{row['fn_far']}"
              + (f"  move {row.get('move_px_median', 0):.2f} px" if st.kind == "texture" else "")
              + (f"  unambiguous fg BIoU {100 * row['unamb_biou']:5.1f} (δ/2: {100 * row['unamb_half_biou']:5.1f})"
                 if "unamb_biou" in row else ""), flush=True)

    m0 = model.clone()
    fg0 = torch.zeros(len(m0), dtype=torch.bool)
    cf0, seen0 = _closed_form(m0, scene.train, px, config.mask_lambda)
    base = _headline(m0, cf0 & seen0, test, gts)
    print(f"{scene_name} / {method} / {obj}: {len(m0)} Gaussians, {len(scene.train)} views, "
          f"closed-form labels on the unrefined scene: IoU {100 * base['iou']:.1f} BIoU {100 * base['biou']:.1f}")
    t0 = time.perf_counter()
    refiner = R.Refiner(m0, scene.train, masks, scene.extent, config, trained["background"], texture_moments=moments)
    refiner.run(progress=False, on_stage_start=start, on_stage_end=end)
    del fg0
    if getattr(config, "object_check", "off") != "off":  # the row's object-render check, as refine() applies it
        from cobgs.refine.consistency import object_render_check

        m = refiner.model
        fg = labels(refiner) > R.FG_THRESHOLD
        kept = object_render_check(m, fg, refiner.views, refiner.pixel_labels, config.mask_lambda, config.backend)
        row = {"stage": len(rows), "kind": "check", "iteration": refiner.iteration, "gaussians": len(m),
               "split": 0, "pruned": 0, "fg": int(kept.sum()), "dropped": int((fg & ~kept).sum())}
        row.update(_headline(m, kept, test, gts))
        rows.append(row)
        print(f"    check   : dropped {row['dropped']} of {int(fg.sum())} foreground Gaussians  IoU "
              f"{100 * row['iou']:5.1f} BIoU {100 * row['biou']:5.1f}", flush=True)
    return {"scene": scene_name, "method": method, "object": obj, "config": config.as_dict(),
            "sets": sets_note, "views": len(scene.train), "start": base, "stages": rows,
            "wall_s": time.perf_counter() - t0}


_PLANS: dict = {}


def wf_plan(wf):
    from pipeline import Plan

    if id(wf) not in _PLANS:
        _PLANS[id(wf)] = Plan(wf)
    return _PLANS[id(wf)]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workflow", default=str(REPO / "workflows" / "synthetic_bench.toml"))
    ap.add_argument("--cache-dir", default=str(REPO / "runs" / "cache"))
    ap.add_argument("--scene", required=True)
    ap.add_argument("--method", default="raem_paper")
    ap.add_argument("--objects", default="", help="comma-separated (default: every object of the scene)")
    ap.add_argument("--set", dest="sets", action="append", default=[], help="KEY=VALUE, as cobgs run --set")
    ap.add_argument("--out", default=str(REPO / "docs" / "benchmarks" / "data" / "trajectory"))
    ap.add_argument("--tag", default="", help="suffix of the output files (a variant's name)")
    a = ap.parse_args(argv)
    os.environ.setdefault("COBGS_SHARED_DATA", str(REPO.parent / "shared" / "data"))
    torch.set_num_threads(max(1, (os.cpu_count() or 2) // 2))
    from pipeline import load_workflow
    from stages.registry import load_registry

    wf = load_workflow(Path(a.workflow), load_registry(), a.sets)
    objs = [o for o in a.objects.split(",") if o] or \
        sorted({t.item["object"] for t in wf_plan(wf).tasks if t.stage.name == "refine" and t.item["scene"] == a.scene
                and t.item["method"] == a.method})
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    for o in objs:
        rec = trajectory(wf, Path(a.cache_dir), a.scene, a.method, o, " ".join(a.sets))
        tag = f"__{a.tag}" if a.tag else ""
        (out / f"{a.scene}__{a.method}__{o}{tag}.json").write_text(json.dumps(rec, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
