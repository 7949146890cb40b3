"""A recorded run for the report tests, made by the real engine in about a second.

The stages here have the names and the artifact layouts of the real DAG (dataset, train,
heldout, refine, segment, evaluate; see stages/_common.py) but none of its work: the
scene is a drawn disc, each method's prediction is that disc moved by a method-specific
amount, and evaluate *measures* IoU / accuracy / boundary IoU of those predictions with
plain numpy, so every number the report shows is computed from the fixture's own masks.
The engine writes the manifests, logs, failure records and cache keys for real.

Two refine tasks fail on purpose (``fail_on``): FlashSplat on s2 (a method missing a whole
scene) and the no-split peer on s1/box (a method with every scene but not every object),
so the report has failures with logs and downstream tasks that never ran.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np
from PIL import Image

from pipeline import Registry, Stage

H, W = 48, 64
VIEWS = ("v000", "v001", "v002", "v003", "v004", "v005")
TEST_VIEWS = ("v000", "v004")
# pixels each method's predicted disc is off by (dx, dy, radius change)
OFFSETS = {"cobgs": (0, 0, 0), "no_bgtr": (1, 0, 0), "delta_03": (0, 1, 1), "nosplit": (2, 1, 1),
           "flashsplat": (1, 2, -2), "sa3d": (3, 0, 2)}

WORKFLOW = """
[workflow]
name = "fixture"
description = "recorded toy run for the report tests"
nested = {{ object = "scene" }}

[params.dataset]
protocol = "{protocol}"

[axes.scene.{scene1}]
[axes.scene.{scene2}]

[axes.method.cobgs]
[axes.method.no_bgtr]
refine = {{ cobgs = {{ bgtr = false }} }}
[axes.method.delta_03]
refine = {{ cobgs = {{ delta = 0.3 }} }}
[axes.method.nosplit]
refine = {{ method = "nosplit", fail_on = "{fail_on}" }}
[axes.method.flashsplat]
refine = {{ method = "flashsplat", fail_on = "{fail_on}" }}

[axes.object.{scene1}.ball]
[axes.object.{scene1}.box]
[axes.object.{scene2}.ball]
"""


def write_workflow(folder: Path, protocol: str = "exact", fail_on: str = "s2/flashsplat/ball,s1/nosplit/box",
                   scenes: tuple[str, str] = ("s1", "s2")) -> Path:
    path = Path(folder) / "fixture.toml"
    path.write_text(WORKFLOW.format(protocol=protocol, fail_on=fail_on, scene1=scenes[0], scene2=scenes[1]))
    return path


def _png(path: Path, arr: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if arr.dtype == np.bool_:
        arr = arr.astype(np.uint8) * 255
    Image.fromarray(arr).save(path)


def _disc(cx: float, cy: float, r: float) -> np.ndarray:
    yy, xx = np.mgrid[0:H, 0:W]
    return (xx - cx) ** 2 + (yy - cy) ** 2 <= r * r


def _gt(scene: str, obj: str, view: str) -> np.ndarray:
    k = VIEWS.index(view)
    base = {"ball": (22.0, 24.0, 9.0), "box": (44.0, 20.0, 7.0)}[obj]
    return _disc(base[0] + k, base[1] + (1 if scene.endswith("2") else 0), base[2])


def _image(view: str) -> np.ndarray:
    yy, xx = np.mgrid[0:H, 0:W]
    img = np.stack([60 + 2 * xx, 80 + 2 * yy, np.full_like(xx, 120)], -1).astype(np.float64)
    for obj, rgb in (("ball", (40, 200, 120)), ("box", (220, 120, 40))):
        img[_gt("s1", obj, view)] = rgb
    return img.clip(0, 255).astype(np.uint8)


def _boundary(m: np.ndarray, d: int) -> np.ndarray:
    p = np.pad(m, 1)
    inner = m.copy()
    for _ in range(d):
        p = np.pad(inner, 1)
        inner = inner & p[:-2, 1:-1] & p[2:, 1:-1] & p[1:-1, :-2] & p[1:-1, 2:]
    return m & ~inner


def _scores(pred: np.ndarray, gt: np.ndarray) -> dict:
    tp, fp = int((pred & gt).sum()), int((pred & ~gt).sum())
    fn = int((~pred & gt).sum())
    d = max(1, round(0.02 * (H * H + W * W) ** 0.5))
    bp, bg = _boundary(pred, d), _boundary(gt, d)
    union = int((bp | bg).sum())
    return {"iou": tp / max(1, tp + fp + fn), "acc": float((pred == gt).mean()),
            "biou": int((bp & bg).sum()) / union if union else 1.0, "tp": tp, "fp": fp, "fn": fn}


# -- stages ------------------------------------------------------------------------------
@dataclass(frozen=True)
class DatasetParams:
    protocol: str = "exact"


def run_dataset(ctx, inputs):
    scene = ctx.item["scene"]
    objs = ["ball", "box"] if scene.endswith("1") else ["ball"]
    spec = {"format": "cobgs-dataset", "version": 1, "scene": scene, "kind": "synthetic",
            "protocol": ctx.params.protocol, "objects": objs, "views": list(VIEWS), "test_views": list(TEST_VIEWS),
            "scene_type": "forward"}
    if ctx.params.protocol == "nvos":
        spec["nvos"] = {"task": scene, "target": TEST_VIEWS[0]}
    (ctx.out_dir / "dataset.json").write_text(json.dumps(spec))
    return {"dataset": ctx.out_dir}


def run_train(ctx, inputs):
    for v in TEST_VIEWS:
        _png(ctx.out_dir / "renders" / f"{v}.png", (_image(v) * 0.9).astype(np.uint8))
    (ctx.out_dir / "train.json").write_text(json.dumps({
        "iterations": 100, "num_gaussians": 5000, "train_views": [v for v in VIEWS if v not in TEST_VIEWS],
        "test_views": list(TEST_VIEWS), "eval": {"psnr": 24.5, "ssim": 0.81}, "wall_s": 0.01, "s_per_it": 1e-4}))
    return {"scene": ctx.out_dir}


@dataclass(frozen=True)
class HeldoutParams:
    max_views: int = 3


def run_heldout(ctx, inputs):
    scene, obj = ctx.item["scene"], ctx.item["object"]
    views = []
    for v in TEST_VIEWS:
        _png(ctx.out_dir / "image" / f"{v}.png", _image(v))
        _png(ctx.out_dir / "gt" / f"{v}.png", _gt(scene, obj, v))
        views.append({"name": v, "image": f"image/{v}.png", "gt": f"gt/{v}.png", "image_size": [H, W],
                      "gt_size": [H, W], "gt_area_px": int(_gt(scene, obj, v).sum())})
    (ctx.out_dir / "heldout.json").write_text(json.dumps({
        "format": "cobgs-heldout", "version": 1, "scene": scene, "object": obj, "protocol": "exact",
        "held_out": len(views), "views": views, "skipped": {}}))
    return {"heldout": ctx.out_dir}


@dataclass(frozen=True)
class CobgsOptions:
    delta: Optional[float] = None
    bags: bool = True
    bgtr: bool = True
    raem: str = "released"
    record_scores: bool = True


@dataclass(frozen=True)
class RefineParams:
    method: str = "cobgs"
    cobgs: CobgsOptions = field(default_factory=CobgsOptions)
    fail_on: str = ""


def run_refine(ctx, inputs):
    p = ctx.params
    if ctx.item.id in p.fail_on.split(","):
        print("fixture refine: about to fail on purpose")
        raise RuntimeError(f"fixture: simulated failure of {ctx.item.id}")
    method = ctx.item["method"]
    delta = p.cobgs.delta if p.cobgs.delta is not None else 0.5
    rng = np.random.default_rng(len(method) * 7 + len(ctx.item["object"]))
    n0 = 5000
    stages, scores, n = [], {}, n0
    if p.method in ("cobgs", "nosplit"):
        kinds = ["mask", "texture"] * 2 + ["mask"] if p.method == "cobgs" and p.cobgs.bgtr else ["mask"] * 3
        for i, kind in enumerate(kinds):
            if kind == "mask":
                s = np.clip(rng.beta(5, 2, size=n) + 0.05 * i, 0, 1).astype(np.float32)
                amb = int((s < delta).sum())
                split = amb // 2 if p.method == "cobgs" else 0
                scores[f"stage_{len(scores)}"] = s
                stages.append({"kind": "mask", "index": i, "iterations": 8, "gaussians_start": n,
                               "gaussians_end": n + split, "ambiguous": amb, "ambiguous_large": split,
                               "split": split, "pruned": 0, "mean_loss": 0.3 / (i + 1), "wall_s": 0.01})
                n += split
            else:
                stages.append({"kind": "texture", "index": i, "iterations": 8, "gaussians_start": n,
                               "gaussians_end": n, "ambiguous": -1, "ambiguous_large": -1, "split": 0,
                               "pruned": 0, "mean_loss": 0.05, "wall_s": 0.02})
    else:
        stages.append({"kind": "flashsplat_vote", "index": 0, "iterations": 6, "gaussians_start": n,
                       "gaussians_end": n, "ambiguous": -1, "ambiguous_large": -1, "split": 0, "pruned": 0,
                       "mean_loss": None, "wall_s": 0.005})
    amb_final = stages[-1]["ambiguous"] if stages[-1]["kind"] == "mask" else -1
    np.savez_compressed(ctx.out_dir / "stage_scores.npz", **scores)
    (ctx.out_dir / "refine.json").write_text(json.dumps({
        "method": p.method, "object": ctx.item["object"], "num_gaussians_start": n0, "num_gaussians_end": n,
        "splits": sum(s["split"] for s in stages), "pruned": 0, "ambiguous_final": amb_final,
        "wall_s": 0.1 + 0.01 * len(stages), "peak_mem_bytes": 1 << 20, "stages": stages,
        "delta": delta if p.method in ("cobgs", "nosplit") else None}))
    return {"refined": ctx.out_dir}


def run_segment(ctx, inputs):
    scene, method, obj = ctx.item["scene"], ctx.item["method"], ctx.item["object"]
    dx, dy, dr = OFFSETS[method]
    for v in TEST_VIEWS:
        g = _gt(scene, obj, v)
        ys, xs = np.nonzero(g)
        pred = _disc(xs.mean() + dx, ys.mean() + dy, (xs.max() - xs.min()) / 2 + dr)
        _png(ctx.out_dir / "pred_masks" / f"{v}.png", pred)
        # as the real segment stage: the visible part (a thin occluder at columns 30-31),
        # which the exact protocol scores
        visible = pred.copy()
        visible[:, 30:32] = False
        _png(ctx.out_dir / "pred_visible" / f"{v}.png", visible)
        img = _image(v)
        _png(ctx.out_dir / "render" / f"{v}.png", img)
        _png(ctx.out_dir / "object" / f"{v}.png", np.where(pred[..., None], img, 0).astype(np.uint8))
        _png(ctx.out_dir / "removed" / f"{v}.png", np.where(pred[..., None], 90, img).astype(np.uint8))
    (ctx.out_dir / "segment.json").write_text(json.dumps({
        "views": list(TEST_VIEWS), "object_gaussians": 300, "extract_ms": 1.0}))
    return {"segmentation": ctx.out_dir}


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(((a.astype(np.float64) - b.astype(np.float64)) ** 2).mean())
    return 10 * np.log10(255.0 ** 2 / mse) if mse > 0 else 60.0


def run_evaluate(ctx, inputs):
    seg, ref = Path(inputs["segmentation"]), json.loads((Path(inputs["refined"]) / "refine.json").read_text())
    per, skipped = {}, {}
    for v in TEST_VIEWS:
        if ctx.item["object"] == "box" and v == "v004":  # as LERF-mask's views without GT
            skipped[v] = "empty GT"
            continue
        pred = np.asarray(Image.open(seg / "pred_visible" / f"{v}.png")) > 128
        per[v] = _scores(pred, _gt(ctx.item["scene"], ctx.item["object"], v))
    vanilla = float(np.mean([_psnr(np.asarray(Image.open(Path(inputs["scene"]) / "renders" / f"{v}.png")),
                                   _image(v)) for v in TEST_VIEWS]))
    psnr = vanilla + (0.1 if ctx.item["method"] == "cobgs" else -0.05 * len(ctx.item["method"]) / 5)
    row = {"protocol": "exact", "scene": ctx.item["scene"], "method": ctx.item["method"],
           "object": ctx.item["object"], "method_kind": ref["method"],
           "iou": float(np.mean([s["iou"] for s in per.values()])),
           "acc": float(np.mean([s["acc"] for s in per.values()])),
           "biou": float(np.mean([s["biou"] for s in per.values()])), "views": len(per), "mask_render": "visible",
           "psnr": psnr, "psnr_vanilla": vanilla, "psnr_delta": psnr - vanilla, "num_gaussians_vanilla": 5000,
           "psnr_before_raem": psnr, "psnr_delta_before_raem": psnr - vanilla,  # the toy RAEM removes nothing
           "num_gaussians": ref["num_gaussians_end"], "object_gaussians": 300, "splits": ref["splits"],
           "pruned": 0, "ambiguous_final": ref["ambiguous_final"], "refine_s": ref["wall_s"],
           "refine_peak_mem_bytes": ref["peak_mem_bytes"], "extract_ms": 1.0}
    (ctx.out_dir / "metrics.json").write_text(json.dumps({"row": row, "details": {"per_view": per, "skipped": skipped},
                                                          "psnr_per_view": {}}))
    return {"metrics": ctx.out_dir}


STAGES = (
    Stage(name="dataset", version=1, run=run_dataset, inputs=(), outputs=("dataset",), params=DatasetParams,
          level=("scene",), description="fixture dataset spec"),
    Stage(name="train", version=1, run=run_train, inputs=("dataset",), outputs=("scene",), level=("scene",),
          uses_device=True, description="fixture vanilla scene"),
    Stage(name="heldout", version=1, run=run_heldout, inputs=("dataset",), outputs=("heldout",),
          params=HeldoutParams, level=("scene", "object"), description="fixture held-out views"),
    Stage(name="refine", version=1, run=run_refine, inputs=("dataset", "scene"), outputs=("refined",),
          params=RefineParams, level=("scene", "method", "object"), uses_device=True,
          description="fixture refinement"),
    Stage(name="segment", version=1, run=run_segment, inputs=("refined",), outputs=("segmentation",),
          level=("scene", "method", "object"), description="fixture segmentation"),
    Stage(name="evaluate", version=1, run=run_evaluate, inputs=("scene", "refined", "segmentation"),
          outputs=("metrics",), level=("scene", "method", "object"), description="fixture evaluation"),
)


def registry() -> Registry:
    """The fixture's stages alone (the built-in ones reuse the same names)."""
    reg = Registry()
    for st in STAGES:
        reg.add(st)
    return reg


def run(folder: Path, **workflow_kw) -> tuple[Path, Path]:
    """Write the fixture workflow into ``folder`` and run it; returns (workflow, cache)."""
    import io

    from pipeline import RunOptions, load_workflow, run_workflow

    wf_path = write_workflow(folder, **workflow_kw)
    cache = Path(folder) / "cache"
    wf = load_workflow(wf_path, registry(), [])
    t0 = time.perf_counter()
    run_workflow(wf, RunOptions(cache_dir=cache, package_version="fixture"), stream=io.StringIO())
    assert time.perf_counter() - t0 < 60
    return wf_path, cache


class Recorded:
    """A finished fixture run: its workflow file, cache and stage registry."""

    def __init__(self, folder: Path, **workflow_kw):
        self.folder = folder
        self.workflow, self.cache = run(folder, **workflow_kw)
        self.registry = registry()

    def build(self, out: Path, **kw) -> Path:
        from stages.commands.report import build_report

        return build_report(self.workflow, out_dir=out, cache_dir=self.cache, registry=self.registry, **kw)
