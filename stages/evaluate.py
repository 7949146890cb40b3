"""Stage ``evaluate``: the scene's protocol (docs/method.md §5) on one method x object.

The dataset spec names the protocol:
  exact      held-out views against the dataset's exact masks (synthetic scenes, Blender
             alpha). Three mask protocols, each on every object (docs/method.md §5):
               headline    the released evaluation render (the object's Gaussians alone,
                           ``pred_masks``) against the object's whole silhouette (amodal
                           GT) where the dataset has it (synthetic scenes; a one-object
                           Blender alpha matte is one), else against the visible GT;
                           ``iou`` / ``acc`` / ``biou``;
               released    the same render against the visible GT (what ``eval_NVOS.py``
                           would score on these views; occluded parts count as errors);
                           ``*_released``;
               occlusion   the occlusion-aware render (``pred_visible``: occluders block
                           the object, as in the GT) against the visible GT;
                           ``*_occlusion``.
             Views where the GT is empty are skipped and listed, per protocol;
  nvos       the held-out target view against the full-resolution GT (prediction resized
             NEAREST, both > 128); IoU and accuracy (the headline: the released render);
  lerf_mask  every GT file of this prompt (an empty GT scores 0 against a non-empty
             prediction, NaN against an empty one: counted as empty_gt_zero / _nan); IoU
             and boundary IoU averaged over
             views (the summary then averages over prompts); missing / empty GT listed;
  spin       SPIn-NeRF: every annotated view but the prompt view (training views: the peers
             train on the whole capture) against its GT at the GT's size; mean IoU and
             accuracy over them (``iou_pooled``: SA3D's one IoU over the stacked masks);
  none       no mask GT: only the texture numbers.
Texture (paper Table 4): PSNR of the refined scene's held-out renders next to the vanilla
scene's, both 8-bit against the held-out images: ``psnr_before_raem`` on the scene before
RAEM's final pruning (Table 4 has no RAEM) and ``psnr`` after it (equal when RAEM is off or
removed nothing).

Output ``metrics``: ``metrics.json`` (one row: the protocol's means, PSNRs, Gaussian
counts and timings of the refinement, plus per-view details and skipped views) and
``per_view.csv``.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

from cobgs.configs import Files, check_params
from pipeline import Resources, Stage

from ._common import StageInputError, load_scene, nvos_task, object_name, read_json, read_spec, write_json


@dataclass(frozen=True)
class EvaluateParams:
    """Attributes:
        boundary_ratio: boundary IoU width, as a fraction of the image diagonal.
        skip_empty_gt: exact protocol: skip held-out views where the object is not visible.
        warn_psnr_drop_db: warn (console, summary, report) when the refined scene's
            held-out PSNR is more than this below the vanilla scene's.
    """

    boundary_ratio: float = 0.02
    skip_empty_gt: bool = True
    warn_psnr_drop_db: float = 2.0

    RANGES: ClassVar[dict] = {"boundary_ratio": "(0, 0.5]", "warn_psnr_drop_db": "(0, 100]"}

    def __post_init__(self) -> None:
        check_params(self)


#: The mask protocols of the exact-GT scenes, named plainly (metrics.json, summary, report).
PROTOCOL_NAMES = {
    "headline_amodal": "headline: object-only render vs the object's whole silhouette (amodal GT)",
    "headline_visible": "headline: object-only render vs the visible GT",
    "released": "released: object-only render vs the visible GT",
    "occlusion": "occlusion-aware render vs the visible GT",
}


def _amodal_gts(spec: dict, dataset_dir: Path, obj: str, visible: dict):
    """{view: amodal GT or None} of ``obj`` on the held-out views, or None where the
    dataset has no amodal GT of it (the headline then scores against the visible GT)."""
    from cobgs.evaluate.protocols import read_mask_u8

    info = spec.amodal or {}
    if obj not in (info.get("objects") or []):
        return None
    if info.get("source") == "visible":
        return dict(visible)
    folder = dataset_dir / info["dir"] / obj
    out = {}
    for n in visible:
        f = folder / f"{n}.png"
        if not f.is_file():
            raise StageInputError(f"{f}: amodal GT of held-out view {n!r} missing (the dataset says "
                                  f"{folder} holds the whole silhouette of {obj!r} per held-out view)")
        out[n] = read_mask_u8(f) > 127
    return out


def _read_preds(folder: Path, names) -> dict:
    from cobgs.evaluate.protocols import read_mask_u8

    out = {}
    for n in names:
        f = folder / f"{n}.png"
        if not f.is_file():
            raise StageInputError(f"{f}: predicted mask missing (segment rendered {sorted(names)[:5]}...)")
        out[n] = read_mask_u8(f)
    return out


def _run(ctx, inputs):
    import numpy as np

    from cobgs.evaluate import protocols as E

    p: EvaluateParams = ctx.params
    spec = read_spec(inputs["dataset"])
    obj = object_name(ctx)
    seg_dir = Path(inputs["segmentation"])
    seg = read_json(seg_dir / Files.SEGMENT)
    ref = read_json(Path(inputs["refined"]) / Files.REFINE)
    train = read_json(Path(inputs["scene"]) / Files.TRAIN)
    scene = load_scene(inputs["dataset"], inputs["poses"])
    test = {v.name: v for v in scene.test}
    missing = sorted(set(test) - set(seg["views"]))
    if missing:
        raise StageInputError(f"segment did not render held-out view(s) {missing[:5]}")
    protocol = spec.protocol
    spin = spec.spin if protocol == "spin" else None
    scored = list(spin["scored"]) if spin else []
    if scored and set(scored) - set(seg["views"]):
        raise StageInputError(f"segment did not render the SPIn-NeRF scored view(s) "
                              f"{sorted(set(scored) - set(seg['views']))[:5]}")
    preds = _read_preds(seg_dir / Files.PRED_MASKS, list(test) + scored)
    row: dict = {"protocol": protocol, "scene": ctx.item["scene"], "method": ctx.item["method"],
                 "object": ctx.item["object"], "dataset_object": obj, "method_kind": ref["method"]}
    details: dict = {}
    if protocol == "exact":
        gts = {n: (v.masks[obj].cpu().numpy() if obj in v.masks else None) for n, v in test.items()}
        amodal = _amodal_gts(spec, Path(inputs["dataset"]), obj, gts)
        visible = _read_preds(seg_dir / Files.PRED_VISIBLE, list(test))
        kw = dict(skip_empty_gt=p.skip_empty_gt, boundary_ratio=p.boundary_ratio)
        occ = E.exact_scores(visible, gts, **kw)
        rel = E.exact_scores(preds, gts, **kw)
        head = E.exact_scores(preds, amodal, **kw) if amodal is not None else rel
        gt_kind = "amodal" if amodal is not None else "visible"
        row.update(iou=head["iou"], acc=head["acc"], biou=head["biou"], views=head["views"],
                   mask_render="object_only", gt=gt_kind, headline=PROTOCOL_NAMES[f"headline_{gt_kind}"],
                   iou_released=rel["iou"], acc_released=rel["acc"], biou_released=rel["biou"],
                   iou_occlusion=occ["iou"], acc_occlusion=occ["acc"], biou_occlusion=occ["biou"])
        details.update(per_view=head["per_view"], skipped=head["skipped"],
                       per_view_released=rel["per_view"], skipped_released=rel["skipped"],
                       per_view_occlusion=occ["per_view"], skipped_occlusion=occ["skipped"],
                       protocols={"headline": PROTOCOL_NAMES[f"headline_{gt_kind}"],
                                  "released": PROTOCOL_NAMES["released"],
                                  "occlusion": PROTOCOL_NAMES["occlusion"]})
    elif protocol == "nvos":
        task = nvos_task(spec, ctx.item["object"], obj)
        s = E.compare_masks(preds[task["target"]], E.read_mask_u8(task["gt_mask"]), p.boundary_ratio)
        row.update(iou=s.iou, acc=s.acc, biou=s.biou, views=1, task=task["task"], mask_render="object_only",
                   gt="visible", headline=PROTOCOL_NAMES["headline_visible"])
        details.update(per_view={task["target"]: s.to_json()}, skipped={})
    elif protocol == "lerf_mask":
        gt = spec.lerf_mask
        paths = {m["view"]: m["path"] for m in gt["masks"] if m["prompt"] == obj}
        if not paths:
            raise StageInputError(f"LERF-mask: no GT file for prompt {obj!r} (prompts: {gt['prompts']})")
        r = E.lerf_prompt_scores(preds, paths, gt["test_views"], p.boundary_ratio)
        row.update(iou=r["iou"], acc=r["acc"], biou=r["biou"], views=r["views"], prompt=obj,
                   mask_render="object_only", gt="visible", headline=PROTOCOL_NAMES["headline_visible"],
                   empty_gt_zero=r["empty_gt_zero"],
                   empty_gt_nan=r["empty_gt_nan"])
        details.update(per_view=r["per_view"], skipped=r["skipped"], empty_gt=r["empty_gt"])
    elif protocol == "spin":
        gts = {v: E.read_mask_u8(f) for v, f in spin["masks"].items()}
        r = E.spin_scores({v: preds[v] for v in scored}, gts, spin["prompt"], p.boundary_ratio)
        row.update(iou=r["iou"], acc=r["acc"], biou=r["biou"], iou_pooled=r["iou_pooled"], views=r["views"],
                   prompt_view=spin["prompt"], mask_render="object_only", gt="visible",
                   headline="SPIn-NeRF: object-only render vs each annotated view's GT but the prompt's")
        details.update(per_view=r["per_view"], skipped={spin["prompt"]: "the prompt view"})
    else:
        row.update(iou=float("nan"), acc=float("nan"), biou=float("nan"), views=0)
        details.update(per_view={}, skipped={})

    refs = {n: v.image.cpu().numpy() for n, v in test.items()}
    refined = {n: E.read_rgb_u8(seg_dir / Files.SCENE_RENDERS / f"{n}.png") for n in test}
    vanilla = {n: E.read_rgb_u8(Path(inputs["scene"]) / Files.RENDERS / f"{n}.png") for n in test}
    pr = E.psnr_scores(refined, refs) if refs else {"psnr": float("nan"), "per_view": {}}
    pv = E.psnr_scores(vanilla, refs) if refs else {"psnr": float("nan"), "per_view": {}}
    pre_dir = seg_dir / Files.BEFORE_RAEM_RENDERS
    pb = pr
    if pre_dir.is_dir() and refs:
        pb = E.psnr_scores({n: E.read_rgb_u8(pre_dir / f"{n}.png") for n in test}, refs)
    row.update(psnr=pr["psnr"], psnr_vanilla=pv["psnr"], psnr_delta=pr["psnr"] - pv["psnr"],
               psnr_before_raem=pb["psnr"], psnr_delta_before_raem=pb["psnr"] - pv["psnr"],
               raem_pruned=ref.get("raem_pruned", 0), dropped=ref.get("dropped", 0),
               skipped_views=ref.get("skipped_views", 0),
               num_gaussians_vanilla=train["num_gaussians"], num_gaussians=ref["num_gaussians_end"],
               object_gaussians=seg["object_gaussians"], splits=ref["splits"], pruned=ref["pruned"],
               ambiguous_final=ref["ambiguous_final"],
               train_psnr_eval=(train.get("eval") or {}).get("psnr"),
               mask_route=ref.get("mask_route"))
    drop = row["psnr_vanilla"] - row["psnr"]
    if np.isfinite(drop) and drop > p.warn_psnr_drop_db:
        msg = (f"the refined scene's held-out PSNR is {row['psnr']:.2f} dB, {drop:.1f} dB below the "
               f"vanilla scene's {row['psnr_vanilla']:.2f} dB: the refinement removed or moved Gaussians "
               f"the views need ({row['pruned']} pruned). Try refine.cobgs.raem = \"off\" (keeps every "
               "ambiguous Gaussian) or \"paper\" (prunes only the smallest), and check the object's masks "
               "(a rough mask spreading onto the background marks background Gaussians as object)")
        row["warnings"] = [msg]
        ctx.warn(msg)
    write_json(ctx.out_dir / Files.METRICS, {"row": row, "details": details,
                                              "psnr_per_view": {"refined": pr["per_view"],
                                                                "vanilla": pv["per_view"],
                                              "before_raem": pb["per_view"]}})
    with open(ctx.out_dir / Files.PER_VIEW, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["view", "iou", "acc", "biou", "biou_released", "biou_occlusion", "psnr", "psnr_before_raem",
                    "psnr_vanilla", "skipped"])
        for n in sorted(set(test) | set(details["per_view"])):
            s = details["per_view"].get(n, {})
            w.writerow([n, s.get("iou", ""), s.get("acc", ""), s.get("biou", ""),
                        details.get("per_view_released", {}).get(n, {}).get("biou", ""),
                        details.get("per_view_occlusion", {}).get(n, {}).get("biou", ""),
                        pr["per_view"].get(n, ""), pb["per_view"].get(n, ""), pv["per_view"].get(n, ""),
                        details["skipped"].get(n, "")])
    ctx.log.info("%s / %s / %s: IoU %.4f, BIoU %.4f, PSNR %.2f (vanilla %.2f) dB", row["scene"], row["method"],
                 row["object"], row["iou"], row["biou"], row["psnr"], row["psnr_vanilla"])
    ctx.note(**{k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in row.items()})
    return {"metrics": ctx.out_dir}


STAGE = Stage(
    name="evaluate", version=6, run=_run, inputs=("dataset", "poses", "scene", "refined", "segmentation"),
    outputs=("metrics",), params=EvaluateParams, level=("scene", "method", "object"),
    resources=Resources(cpus=1),
    description="protocol metrics (exact GT, NVOS, LERF-mask, SPIn-NeRF) and PSNR vs the vanilla scene",
)
