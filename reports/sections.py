"""Which columns each table of the report shows, in which order, formatted how.

The records come from :mod:`reports.results`; this module only lays them out.
"""

from __future__ import annotations

from typing import Optional

from . import fmt, ablation, plotdata, records
from .methods import reference_of
from .collect import RunData
from .tables import Column, Table, build_table


def _gpu_col(*record_lists, title: str = "peak memory of PyTorch's CUDA allocator during the refine "
                                         "task (max over objects)") -> list[Column]:
    """A "Peak GPU" column only when some task ran on a GPU and recorded its peak."""
    if any(r.get("peak_gpu") is not None for recs in record_lists for r in recs):
        return [Column("peak_gpu", "Peak GPU", fmt.nbytes, title=title)]
    return []


def _present(key: str, record_lists) -> bool:
    return any(fmt.finite(r.get(key)) is not None for recs in record_lists for r in recs)


def _differs(key: str, base: str, record_lists) -> bool:
    """Some record has ``key`` and it differs from ``base`` (e.g. PSNR before / after RAEM)."""
    return any(fmt.finite(r.get(key)) is not None and r.get(key) != r.get(base)
               for recs in record_lists for r in recs)


def _protocol_cols(*record_lists) -> list[Column]:
    """The released and occlusion-aware protocols' mBIoU beside the headline, where scored."""
    out = []
    if _present("biou_released", record_lists):
        out.append(Column("biou_released", "mBIoU released", fmt.pct, better="max",
                          title="released protocol: the object's Gaussians rendered alone vs the visible GT "
                                "(occluded parts count as errors)"))
    if _present("biou_occlusion", record_lists):
        out.append(Column("biou_occlusion", "mBIoU occl.", fmt.pct, better="max",
                          title="occlusion-aware render (occluders hide the object) vs the visible GT"))
    return out


def _psnr_cols(*record_lists) -> list[Column]:
    before = []
    if _differs("psnr_before_raem", "psnr", record_lists):
        before = [Column("psnr_before_raem", "PSNR pre-RAEM", fmt.db, better="max",
                         title="refined scene before RAEM's final pruning, held-out views (dB): paper Table 4"),
                  Column("psnr_delta_before_raem", "ΔPSNR pre-RAEM", lambda v: fmt.db(v, signed=True),
                         better="max", title="before-RAEM minus vanilla scene PSNR (dB)")]
    return before + [
        Column("psnr", "PSNR", fmt.db, better="max", title="refined scene after the method (RAEM included), "
                                                            "held-out views (dB)"),
        Column("psnr_delta", "ΔPSNR", lambda v: fmt.db(v, signed=True), better="max",
               title="refined minus vanilla scene PSNR on the same views (dB)")]


def _cols_metrics(*record_lists) -> list[Column]:
    return [
        Column("iou", "mIoU", fmt.pct, better="max", title="headline protocol (the object's Gaussians rendered "
               "alone vs its whole silhouette where known, else the visible GT): mean IoU (%), over objects, "
               "then scenes"),
        Column("acc", "mAcc", fmt.pct, better="max", title="headline protocol: mean pixel accuracy (%)"),
        Column("biou", "mBIoU", fmt.pct, better="max", title="headline protocol: mean boundary IoU (%), width 2% "
               "of the diagonal"),
        *_protocol_cols(*record_lists),
        *_psnr_cols(*record_lists),
        Column("num_gaussians", "Gaussians", fmt.count, title="scene size after the method (mean over objects)"),
        Column("refine_s", "Refine time", fmt.seconds, better="min", title="wall time of the method per object"),
        Column("peak_rss", "Peak RSS", fmt.nbytes,
               title="peak resident memory of the process that ran the refine task (host memory, max over "
                     "objects; with --jobs 1 this includes the driver's own footprint, so it is not ranked)"),
    ] + _gpu_col(*record_lists)


def _quoted(key: str, label: str, pct: bool = True) -> Column:
    return Column(key, label + " †", (lambda v: fmt.pct(v, 1)) if pct else fmt.db, quoted=True,
                  title="quoted from the paper, not measured here")


def result_tables(data: RunData, infos: dict, logs: records.LogHref) -> dict:
    by_method, notes = records.method_records(data, infos, logs)
    by_scene = records.scene_method_records(data, infos, logs)
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
                "differ from the refine stage's defaults"), Column("scenes", "Scenes", fmt.count),
         Column("objects", "Objects", fmt.count, title="scene x object items with metrics")]
        + _cols_metrics(by_method) + paper_m + [status], by_method,
        notes=notes + ["Best values are shaded and bold, among methods with every scene and object "
                       "done (a mean over fewer is not comparable); not marked when all are equal."])
    t_scene = build_table(
        "t-scene", "Results per scene × method (mean over the scene's objects); best per scene marked",
        [Column("scene", "Scene", numeric=False),
         *([Column("masks", "Masks", numeric=False, title="how the training masks were made; a scene that mixes "
                   "exact and noisy masks gets one row per kind (never averaged together)")]
           if any(r.get("masks") for r in by_scene) else []),
         Column("method", "Method", numeric=False),
         Column("objects", "Objects", fmt.count)] + _cols_metrics(by_scene) + paper_s + [status], by_scene,
        group_by="_group", notes=[n for n in notes if paper_s])
    recs = records.object_records(data, infos, logs)
    for r in recs:  # best values per (scene, object): objects differ too much to compare across
        r["_group"] = f"{r['scene']}/{r['object']}"
    t_object = build_table(
        "t-object", "Per object: the evaluate stage's numbers and the refinement's Gaussian bookkeeping",
        [Column("scene", "Scene", numeric=False), Column("method", "Method", numeric=False),
         Column("object", "Object", numeric=False),
         Column("mask_route", "Masks", numeric=False,
                title="how the training masks were made: dataset masks, released masks (files), "
                      "scribbles -> SAM2, text -> two-stage (+ noise)"),
         Column("iou", "IoU", fmt.pct, better="max"),
         Column("acc", "Acc", fmt.pct, better="max"), Column("biou", "BIoU", fmt.pct, better="max"),
         *_protocol_cols(recs),
         Column("views", "Views", fmt.count, title="held-out views evaluated (hover for skipped ones)"),
         *_psnr_cols(recs),
         Column("num_gaussians", "Gaussians", fmt.count), Column("splits", "Splits", fmt.count),
         Column("pruned", "Pruned", fmt.count, title="Gaussians deleted from the scene (COB-GS: RAEM)"),
         *([Column("dropped", "Dropped", fmt.count, title="Gaussians taken out of the optimisation but kept in "
                   "the scene (SA3D-GS: label <= 0 after its first pass)")] if any(
             r.get("dropped") for r in recs) else []),
         Column("ambiguous_final", "Ambiguous", fmt.count, title="Gaussians with score < δ at the end, before RAEM"),
         Column("refine_s", "Refine time", fmt.seconds, better="min"), Column("peak_rss", "Peak RSS", fmt.nbytes)]
        + _gpu_col(recs) + [status], recs, group_by="_group")
    t_scenes = build_table(
        "t-scenes", "Scenes: data and the baseline 3DGS every method starts from",
        [Column("scene", "Scene", numeric=False), Column("kind", "Kind", numeric=False),
         Column("protocol", "Protocol", numeric=False), Column("scene_type", "Type", numeric=False),
         Column("views", "Views", fmt.count), Column("test_views", "Held out", fmt.count),
         Column("objects", "Objects", numeric=False, wrap=True), Column("iterations", "Iterations", fmt.count),
         Column("num_gaussians", "Gaussians", fmt.count), Column("train_s", "Train time", fmt.seconds),
         Column("psnr", "PSNR", fmt.db, title="vanilla scene, held-out views (dB)"),
         Column("ssim", "SSIM", lambda v: "" if fmt.finite(v) is None else f"{v:.4f}"),
         Column("status", "Training", numeric=False),
         Column("notes", "Notes", numeric=False, wrap=True,
                title="the training recipe, and what the reader decided about the data: distortion "
                      "read as a pinhole, images matched to poses by sorted order, ...")], records.scene_records(data))
    ref = reference_of(infos)
    drecs, compared = records.difference_records(data, infos, ref)
    t_diff = build_table(
        "t-diff", f"mBIoU of {ref} minus each peer's (and the faithful COB-GS row's where {ref} is a variant of it), per scene (headline protocol; points, 95 % interval from "
                  "resampling the held-out views of each object)",
        [Column("scene", "Scene", numeric=False),
         *([Column("masks", "Masks", numeric=False)] if any(r.get("masks") for r in drecs) else []),
         *[Column(f"d:{m}", f"− {m}", lambda v: fmt.db(v, signed=True),
                  title=f"{ref}'s mBIoU minus {m}'s on the same objects and views") for m in compared]],
        drecs if compared else [],
        notes=["An interval entirely below 0 means the reference is significantly below that method on the "
               "scene; entirely above, significantly above."]) if compared else None
    arecs = ablation.ablation_records(by_scene, infos)
    masks_col = [Column("masks", "Masks", numeric=False)] if any(r.get("masks") for r in by_scene) else []
    t_ablation = build_table(
        "t-ablation", "Ablation (paper Table 5) per scene: the three components switched on one at a time "
                      "(no-split = none of them), and the stages other methods add to COB-GS; headline protocol "
                      "unless named",
        [Column("scene", "Scene", numeric=False), *masks_col, Column("method", "Method", numeric=False),
         Column("bags", "BAGS", numeric=False, title="boundary-adaptive Gaussian splitting"),
         Column("bgtr", "BGTR", numeric=False, title="texture stages between the mask stages"),
         Column("raem", "RAEM", numeric=False, title="final pruning of ambiguous Gaussians: off, released (every "
                "ambiguous Gaussian) or paper (only those below the pixel footprint)"),
         *([Column("check", "Object check", numeric=False,
                   title="this project's object-render check (docs/method.md §7), not the paper's: the "
                         "foreground rendered alone, what falls on the masks' background leaves it")]
           if any(r.get("check") for r in arecs) else []),
         *([Column("stage", "Added stage", numeric=False,
                   title="a stage another method adds to COB-GS's, on the switches to its left (NG-GS: its "
                         "NeRF-guided boundary loss in the texture stages, docs/method.md §3)")]
           if any(r.get("stage") for r in arecs) else []),
         Column("iou", "mIoU", fmt.pct, better="max"), Column("acc", "mAcc", fmt.pct, better="max"),
         Column("biou", "mBIoU", fmt.pct, better="max"), *_protocol_cols(arecs),
         Column("psnr_delta", "ΔPSNR", lambda v: fmt.db(v, signed=True), better="max",
                title="refined minus vanilla scene PSNR on the same views (dB)"),
         Column("num_gaussians", "Gaussians", fmt.count)], arecs, group_by="_group",
        notes=["The paper's Table 5 (NVOS, mIoU / mAcc): none 91.2 / 98.3, BAGS 91.9 / 98.5, BAGS + BGTR "
               "91.9 / 98.4, all three 92.1 / 98.6 — another dataset, quoted for the trend only."]) if arecs else None
    precs = ablation.psnr_records(by_scene, infos, ref)
    d = lambda v: fmt.db(v, signed=True)  # noqa: E731
    t_psnr = build_table(
        "t-psnr", "Texture quality (paper Table 4) per scene: held-out PSNR (dB) of the vanilla scene and after "
                  "each part of the refinement (means over the scene's objects)",
        [Column("scene", "Scene", numeric=False), *masks_col,
         Column("vanilla", "Vanilla", fmt.db, title="the trained 3DGS scene every method starts from"),
         Column("mask_only", "M.O", fmt.db, title="mask stages only (BAGS, no texture stages, RAEM off): "
                "paper's 'M.O'"),
         Column("joint", "M.O + T.O", fmt.db, title="mask and texture stages, before RAEM's final pruning "
                "(the reference's scene): paper's 'M.O+T.O', what Table 4 measures"),
         Column("raem_released", "+ RAEM released", fmt.db, title="the same after RAEM (released variant)"),
         Column("raem_paper", "+ RAEM paper", fmt.db, title="after RAEM (paper variant)"),
         *[Column(f"d_{k}", f"Δ {label}", d, title=f"{label} minus vanilla (dB)")
           for k, label in (("mask_only", "M.O"), ("joint", "M.O + T.O"), ("raem_released", "RAEM released"),
                            ("raem_paper", "RAEM paper"))],
         Column("target", "≥ vanilla − 0.1", numeric=False, title="Table 4's bar on the scene before RAEM")],
        precs, notes=["The paper's Table 4 (NVOS means): vanilla 23.06, M.O 22.61, T.O 23.07, M.O+T.O 23.13 dB. "
                      "Its T.O column (texture stages without splitting) has no row here."]) if precs else None
    t_spin = _spin_table(data, by_scene)
    return {"method": t_method, "scene": t_scene, "object": t_object, "scenes": t_scenes, "diff": t_diff,
            "ablation": t_ablation, "psnr": t_psnr, "spin": t_spin,
            "raw": {"by_method": by_method, "by_scene_method": by_scene, "by_object": recs,
                    **({"differences": drecs} if compared else {}),
                    **({"ablation": arecs} if arecs else {}), **({"texture_psnr": precs} if precs else {})}}


def _spin_table(data: RunData, by_scene: list) -> Optional[Table]:
    """SPIn-NeRF: per scene, SPIn-NeRF's published row (README_MVSeg.txt, marked as published)
    above the methods measured here, and the means over the scenes this run has."""
    from . import paper

    scenes = [n for n, sc in data.scenes.items() if sc.protocol == "spin"]
    if not scenes:
        return None
    key = {n: str(((data.scenes[n].dataset or {}).get("spin") or {}).get("scene") or n) for n in scenes}
    rows = []
    for n in scenes:
        q = paper.spin_published(key[n])
        if q is not None:
            rows.append({"scene": n, "method": f"{q.label} (published)", "pub_iou": q.values["iou"] / 100.0,
                         "pub_acc": q.values["acc"] / 100.0, "_group": n, "_class": {"method": ["quoted"]},
                         "_title": {"pub_iou": q.source, "pub_acc": q.source}})
        for r in by_scene:
            if r.get("scene") == n:
                pooled = [x.row.get("iou_pooled") for x in data.results
                          if x.ok and x.scene == n and x.method == r["method"] and x.row.get("iou_pooled") is not None]
                rows.append({"scene": n, "method": r["method"], "iou": r.get("iou"), "acc": r.get("acc"),
                             "iou_pooled": sum(pooled) / len(pooled) if pooled else None, "status": r.get("status"),
                             "_group": n})
    q = paper.spin_published_mean([key[n] for n in scenes])
    if q is not None:
        rows.append({"scene": f"mean of {len(scenes)}", "method": f"{q.label} (published)",
                     "pub_iou": q.values["iou"] / 100.0, "pub_acc": q.values["acc"] / 100.0, "_group": "mean",
                     "_class": {"method": ["quoted"]}, "_title": {"pub_iou": q.source, "pub_acc": q.source}})
    for q in paper.spin_peer_means():  # each over its paper's own scenes: beside the means, not the scenes
        rows.append({"scene": "paper's scenes", "method": f"{q.label} (published ‡)", "pub_iou": q.values["iou"] / 100.0,
                     "pub_acc": q.values["acc"] / 100.0, "_group": "peers", "_class": {"method": ["quoted"]},
                     "_title": {"pub_iou": q.source, "pub_acc": q.source}})
    return build_table(
        "t-spin", "SPIn-NeRF multiview segmentation: each scene's published SPIn-NeRF row (†) above the methods "
                  "run here (every annotated view but the prompt view; mean IoU / accuracy over the views)",
        [Column("scene", "Scene", numeric=False), Column("method", "Method", numeric=False),
         Column("iou", "mIoU", fmt.pct, better="max"), Column("acc", "mAcc", fmt.pct, better="max"),
         Column("iou_pooled", "pooled IoU", fmt.pct, title="SA3D's lib/evaluate.py: one IoU over the scene's "
                "stacked masks"),
         Column("pub_iou", "published IoU †", lambda v: fmt.pct(v, 2), quoted=True,
                title="published, not measured here"),
         Column("pub_acc", "published Acc †", lambda v: fmt.pct(v, 2), quoted=True,
                title="published, not measured here"),
         Column("status", "Status", numeric=False)], rows, group_by="_group",
        notes=["† SPIn-NeRF's own numbers as its annotation release prints them (README_MVSeg.txt, 'Our "
               "results'), with its own 3D method and prompts: quoted, never ranked. fork is published but its "
               "RGB is not public, so no run here covers it.",
               "‡ The peers' means over their papers' own scene sets, as SAGOnline's Table I prints them "
               "(arXiv 2508.08219v2; SAGOnline's own row, and its quotes of SAGA, SA3D-GS and SA3D, whose own "
               "papers were not read here): quoted, never ranked, and not a mean over this run's scenes."])


def detail_tables(data: RunData, ref: Optional[str], logs: records.LogHref) -> tuple[Table, Table]:
    """The per-stage statistics of the reference method's refinement, and every task."""
    stage_table = build_table(
        "t-refine-stages", f"Refinement stages of {ref}: ambiguous Gaussians and splits per stage",
        [Column("scene", "Scene", numeric=False), Column("object", "Object", numeric=False),
         Column("index", "Stage", fmt.count), Column("kind", "Kind", numeric=False),
         Column("iterations", "Iterations", fmt.count), Column("g_start", "Gaussians in", fmt.count),
         Column("g_end", "Gaussians out", fmt.count), Column("ambiguous", "Ambiguous", fmt.count),
         Column("ambiguous_large", "Ambiguous, splittable", fmt.count), Column("split", "Split", fmt.count),
         Column("pruned", "Pruned", fmt.count),
         Column("loss", "Mean loss", lambda v: "" if fmt.finite(v) is None else f"{v:.4f}"),
         Column("wall_s", "Time", fmt.seconds)], plotdata.refine_stage_records(data, ref))
    tasks = records.task_records(data, logs)
    task_table = build_table(
        "t-tasks", "Every task of the workflow: state, cache key, cost",
        [Column("order", "#", fmt.count), Column("stage", "Stage", numeric=False),
         Column("item", "Item", numeric=False), Column("state", "State", numeric=False),
         Column("key", "Cache key", fmt.short_key, numeric=False), Column("version", "v", fmt.count),
         Column("wall_s", "Wall", fmt.seconds), Column("cpu_s", "CPU", fmt.seconds),
         Column("peak_rss", "Peak RSS", fmt.nbytes)] + _gpu_col(tasks, title="PyTorch CUDA allocator peak during the task") + [Column("host", "Host", numeric=False),
         Column("device", "Device", numeric=False), Column("started", "Started", fmt.timestamp),
         Column("log", "Log", numeric=False)], tasks)
    return stage_table, task_table
