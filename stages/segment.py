"""Stage ``segment``: extract the object and render the held-out views (scene x method x object).

Output ``segmentation``:
  object.ply, background.ply   the object's Gaussians and the scene with the object removed,
                               standard 3DGS layout (no extras: any splat viewer opens them)
  pred_masks/<view>.png        predicted object mask as the released evaluation renders it: the
                               object's Gaussians alone, mask channel above the method's bar
                               (0.5; SA3D-GS's official render: 0.1) — the headline protocol
  pred_visible/<view>.png      the object's visible mask: every Gaussian rendered, occluders
                               block the object (the exact-GT protocol; cobgs.evaluate.protocols)
  render/<view>.png            the refined scene (texture quality vs the vanilla scene)
  render_before_raem/<view>.png  the refined scene before RAEM's pruning (only when RAEM
                               removed Gaussians; paper Table 4 measures texture there)
  object/<view>.png            the object alone
  removed/<view>.png           the scene without the object
  segment.json                 Gaussian counts, extraction time (ms), render time, views
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, Optional

from cobgs.configs import Files, check_params
from pipeline import Resources, Stage

from ._common import load_scene, read_json, read_spec, to_device, torch_device, write_json, write_png


@dataclass(frozen=True)
class SegmentParams:
    """Attributes:
        mask_threshold: the rendered object mask is foreground above this; None = the
            method's own bar (COB-GS, FlashSplat and the strict SA3D-GS: 0.5 as docs/method.md §2;
            SA3D-GS's official render: 0.1 on its composited raw labels).
        views: "test" (the held-out views) or "all" (training views too).
        backend: rasterizer backend.
    """

    mask_threshold: Optional[float] = None
    views: str = "test"
    backend: str = "native"

    RANGES: ClassVar[dict] = {"mask_threshold": "(0, 1)"}  # the rendered mask is in [0, 1]
    CHOICES: ClassVar[dict] = {"backend": ("native", "reference"), "views": ("test", "all")}

    def __post_init__(self) -> None:
        check_params(self)


def read_refined(rdir: Path, device) -> tuple:
    """A refine entry's output folder as this stage reads it: ``(result, in_scene, seg)``, the
    :class:`cobgs.refine.result.RefineResult` of the object alone, the same with the object's
    in-scene set as its foreground (the refinement's own where it kept one, ``object_check =
    "per_use"``; else the same result), and the segmentation arrays (``segmentation.npz``)."""
    import numpy as np
    import torch

    from cobgs.gaussians.ply import load_ply
    from cobgs.refine.result import RefineResult

    rdir = Path(rdir)
    info = read_json(rdir / Files.REFINE)
    model = load_ply(rdir / Files.REFINED_PLY, device=device)
    seg = np.load(rdir / Files.SEGMENTATION)
    result = RefineResult(method=info["method"], object_name=info["object"], model=model,
                          foreground=torch.from_numpy(seg["foreground"]).to(device),
                          background=torch.from_numpy(seg["background"]).to(device),
                          mask_values=torch.from_numpy(seg["mask_values"]).to(device),
                          mask_threshold=info.get("mask_threshold"), mask_render=info.get("mask_render", "object"))
    in_scene = result if "foreground_in_scene" not in seg.files else dataclasses.replace(
        result, foreground=torch.from_numpy(seg["foreground_in_scene"]).to(device))
    return result, in_scene, seg


def _run(ctx, inputs):
    import torch

    from cobgs.gaussians.ply import load_ply, save_ply
    from cobgs.refine.segment import (extract, method_threshold, render_object_mask, render_object_rgb, render_removed_rgb,
                               visible_object_mask)
    from cobgs.render.image import render_image

    p: SegmentParams = ctx.params
    dev = torch_device(ctx.device)
    spec = read_spec(inputs["dataset"])
    rdir = Path(inputs["refined"])
    bg = read_json(Path(inputs["scene"]) / Files.TRAIN)["background"]
    # in_scene: the object as rendered within the scene (pred_visible)
    result, in_scene, seg = read_refined(rdir, dev)
    model = result.model
    before_raem = None
    if "raem_keep" in seg.files:
        from cobgs.refine.result import restore_pruned

        before_raem = restore_pruned(model, torch.from_numpy(seg["raem_keep"]).to(dev),
                                     load_ply(rdir / Files.RAEM_REMOVED, device=dev))

    t0 = time.perf_counter()
    obj_model = extract(result, "foreground", extras=[])
    rest_model = extract(result, "background", extras=[])
    extract_ms = 1000.0 * (time.perf_counter() - t0)
    cpu = torch.device("cpu")
    save_ply(ctx.out_dir / Files.OBJECT_PLY, obj_model.to(cpu), extras=[])
    save_ply(ctx.out_dir / Files.BACKGROUND_PLY, rest_model.to(cpu), extras=[])

    scene = to_device(load_scene(inputs["dataset"], inputs["poses"]), ctx.device)
    views = scene.test if p.views == "test" else scene.views
    spin = read_spec(inputs["dataset"]).spin
    if spin:  # SPIn-NeRF scores annotated training views: render them too
        have = {v.name for v in views}
        views = list(views) + [v for v in scene.views if v.name in set(spin["scored"]) and v.name not in have]
    t0 = time.perf_counter()
    for v in ctx.progress(views, desc=f"segment[{ctx.item.label}]", unit="view"):
        mask = render_object_mask(result, v.camera, threshold=p.mask_threshold, backend=p.backend)
        write_png(ctx.out_dir / Files.PRED_MASKS / f"{v.name}.png", mask.cpu().numpy())
        visible = visible_object_mask(in_scene, v.camera, threshold=p.mask_threshold, backend=p.backend)
        write_png(ctx.out_dir / Files.PRED_VISIBLE / f"{v.name}.png", visible.cpu().numpy())
        write_png(ctx.out_dir / Files.SCENE_RENDERS / f"{v.name}.png",
                  render_image(model, v.camera, bg, backend=p.backend).clamp(0, 1).cpu().numpy())
        if before_raem is not None:
            write_png(ctx.out_dir / Files.BEFORE_RAEM_RENDERS / f"{v.name}.png",
                      render_image(before_raem, v.camera, bg, backend=p.backend).clamp(0, 1).cpu().numpy())
        write_png(ctx.out_dir / Files.OBJECT_RENDERS / f"{v.name}.png",
                  render_object_rgb(result, v.camera, bg, backend=p.backend).clamp(0, 1).cpu().numpy())
        write_png(ctx.out_dir / Files.REMOVED_RENDERS / f"{v.name}.png",
                  render_removed_rgb(result, v.camera, bg, backend=p.backend).clamp(0, 1).cpu().numpy())
    render_s = time.perf_counter() - t0
    out = {"method": result.method, "object": result.object_name, "scene": ctx.item["scene"],
           "num_gaussians": len(model), "object_gaussians": len(obj_model),
           "num_gaussians_before_raem": len(before_raem) if before_raem is not None else len(model),
           "mask_threshold": method_threshold(result, p.mask_threshold),
           "background_gaussians": len(rest_model), "views": [v.name for v in views],
           "files": {"object": Files.OBJECT_PLY, "background": Files.BACKGROUND_PLY, Files.PRED_MASKS: Files.PRED_MASKS,
                     "pred_visible": Files.PRED_VISIBLE, "render": Files.SCENE_RENDERS,
                     "object_renders": Files.OBJECT_RENDERS, "removed_renders": Files.REMOVED_RENDERS,
                     **({"render_before_raem": Files.BEFORE_RAEM_RENDERS} if before_raem is not None else {})}}
    write_json(ctx.out_dir / Files.SEGMENT, out)
    # (timings in the manifest only: the artifact is the same bytes on a recompute)
    ctx.note(object_gaussians=len(obj_model), background_gaussians=len(rest_model), extract_ms=extract_ms,
             render_s=render_s, views=len(views))
    return {"segmentation": ctx.out_dir}


STAGE = Stage(
    name="segment", version=4, run=_run, inputs=("dataset", "poses", "scene", "refined"),
    outputs=("segmentation",), params=SegmentParams, level=("scene", "method", "object"), uses_device=True,
    resources=Resources(cpus=2),
    description="object / background PLYs and held-out renders (mask, scene, object, removal)",
)
