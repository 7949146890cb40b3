"""Stage ``refine``: COB-GS or a peer on one object of one scene (scene x method x object).

The ``method`` axis holds COB-GS, its ablation rows and the peers as items with param
overrides, e.g. ``[axes.method.no_bags] refine = { cobgs = { bags = false } }`` or
``[axes.method.flashsplat] refine = { method = "flashsplat" }``. Every method starts from
the same trained scene and the same masks (:func:`cobgs.refine.peers.run_method`).

Output ``refined``: ``refined.ply`` (the scene after the method, with its label extras:
``mask_logit`` for COB-GS), ``segmentation.npz`` (``foreground``, ``background`` [N] bool,
``mask_values`` [N] float32 — what the segment stage extracts and renders),
``stage_scores.npz`` (the stage-mean ambiguity score of every Gaussian after each mask
stage: the δ sweep of paper Fig. 7), ``refine.json`` (the method's summary: Gaussian
counts, splits, prunes, per-stage statistics, the method's render threshold, config) and,
when RAEM pruned anything, ``raem_removed.ply`` (the pruned Gaussians, extras included)
with ``raem_keep`` in ``segmentation.npz``: together with ``refined.ply`` they give the
scene before the final pruning, where paper Table 4 measures texture.

COB-GS's texture stages continue the baseline's Adam from the ``adam_moments.pt`` the
train stage writes beside ``scene.ply``; a scene without that file (e.g. a PLY trained
elsewhere) refines with fresh moments, and ``refine.json`` says which (``texture_adam``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

from cobgs.configs import Files, FlashSplatConfig, LUDVIGConfig, NGSConfig, RefineConfig, SA3DConfig, check_params
from cobgs.refine.methods import METHODS, method_for
from pipeline import Resources, Stage

from ._common import (StageInputError, load_scene, masks_for_views, object_name, read_json, read_spec,
                      to_device, torch_device, write_json)


@dataclass(frozen=True)
class RefineParams:
    """Attributes:
        method: "cobgs" (ablations through ``cobgs``), "nosplit", "sa3d", "flashsplat", "ngs"
            (:data:`cobgs.refine.methods.REGISTRY`).
        scene_type: "auto" (the dataset's: forward-facing or 360°), "forward" or "360";
            the scene type of :class:`cobgs.refine.alternation.RefineConfig` (default δ and number of
            stages).
        cobgs: COB-GS parameters (also the no-split peer's, with its switches forced off).
        sa3d: SA3D-GS parameters.
        flashsplat: FlashSplat parameters.
        ngs: NG-GS's boundary stage (method "ngs": COB-GS's stages from ``cobgs`` plus this).
        ludvig: LUDVIG parameters (method "ludvig").
    """

    method: str = "cobgs"
    scene_type: str = "auto"
    cobgs: RefineConfig = field(default_factory=RefineConfig)
    sa3d: SA3DConfig = field(default_factory=SA3DConfig)
    flashsplat: FlashSplatConfig = field(default_factory=FlashSplatConfig)
    ngs: NGSConfig = field(default_factory=NGSConfig)
    ludvig: LUDVIGConfig = field(default_factory=LUDVIGConfig)

    CHOICES: ClassVar[dict] = {"method": METHODS, "scene_type": ("auto", "forward", "360")}

    def __post_init__(self) -> None:
        check_params(self)
        if self.scene_type not in ("auto", "forward", "360"):
            raise ValueError(f"scene_type must be 'auto', 'forward' or '360', got {self.scene_type!r}")
        if self.cobgs.scene_type != RefineConfig.scene_type:
            raise ValueError("set refine.scene_type ('auto' takes the dataset's), not "
                             f"refine.cobgs.scene_type (got {self.cobgs.scene_type!r}): the stage sets it")


def method_config(p: RefineParams, dataset_scene_type: str):
    """The library config object ``p.method``'s :meth:`~cobgs.refine.methods.RefineMethod.run` takes."""
    return method_for(p.method).config_of(p, dataset_scene_type)


def _run(ctx, inputs):
    import numpy as np
    import torch

    from cobgs.train.adam_moments import MOMENTS_FILE, read_moments
    from cobgs.refine.methods import RefineInputs
    from cobgs.gaussians.ply import load_ply, save_ply

    p: RefineParams = ctx.params
    spec = read_spec(inputs["dataset"])
    obj = object_name(ctx)
    dev = torch_device(ctx.device)
    scene = to_device(load_scene(inputs["dataset"], inputs["poses"]), ctx.device)
    trained = read_json(Path(inputs["scene"]) / Files.TRAIN)
    model = load_ply(Path(inputs["scene"]) / Files.SCENE_PLY, device=dev)
    masks = masks_for_views(Path(inputs["masks"]), scene.train)
    if all(m is None for m in masks):
        raise StageInputError(f"no mask of object {obj!r} matches a training view of {spec['scene']!r}")
    masks = [None if m is None else m.to(dev) for m in masks]
    method = method_for(p.method)  # (the one lookup: config, schedule and run are the method's)
    config = method.config_of(p, spec.scene_type)
    sched = method.schedule(config)
    moments = None
    moments_file = Path(inputs["scene"]) / MOMENTS_FILE
    if method.alternates and sched.bgtr and sched.texture_adam == "baseline":
        if moments_file.is_file():
            moments = read_moments(moments_file, len(model), device=dev)
        else:
            ctx.log.warning("%s not found: the texture stages start from fresh Adam moments", moments_file)
    ctx.log.info("%s on %r: %d Gaussians, %d views (%d with a mask)", p.method, obj, len(model),
                 len(scene.train), sum(m is not None for m in masks))
    if method.alternates:
        from cobgs.refine.alternation import short_stage_warning

        short = short_stage_warning(sched, len(scene.train))
        if short:  # on the task's line and in its manifest, also when reused from the cache
            ctx.warn(short)
    result = method.run(RefineInputs(model, scene.train, masks, scene.extent, background=trained["background"],
                                     object_name=obj, texture_moments=moments,
                                     progress=lambda total, desc: ctx.progress(total=total, desc=desc)), config)
    out_model = result.model.to(torch.device("cpu")) if dev.type != "cpu" else result.model
    save_ply(ctx.out_dir / Files.REFINED_PLY, out_model)
    raem = {}  # (and the object-within-the-scene set, where there is one)
    if result.raem_keep is not None and result.raem_removed is not None:
        save_ply(ctx.out_dir / Files.RAEM_REMOVED, result.raem_removed.to(torch.device("cpu")))
        raem = {"raem_keep": result.raem_keep.cpu().numpy().astype(bool)}
    if result.foreground_in_scene is not None:
        raem["foreground_in_scene"] = result.foreground_in_scene.cpu().numpy().astype(bool)
    np.savez_compressed(ctx.out_dir / Files.SEGMENTATION,
                        foreground=result.foreground.cpu().numpy().astype(bool),
                        background=result.background.cpu().numpy().astype(bool),
                        mask_values=result.mask_values.detach().cpu().numpy().astype(np.float32), **raem)
    np.savez_compressed(ctx.out_dir / Files.STAGE_SCORES,
                        **{f"stage_{i}": s.cpu().numpy().astype(np.float32)
                           for i, s in enumerate(result.stage_scores)})
    summary = result.summary()
    # Timings and memory go to the manifest (ctx.note), not the artifact: a recompute with
    # the same result then gives the same bytes, and nothing downstream re-runs.
    timing = {"refine_s": summary.pop("wall_s"), "peak_mem_bytes": summary.pop("peak_mem_bytes"),
              "stage_wall_s": [s.pop("wall_s", None) for s in summary["stages"]]}
    masks_info = read_json(Path(inputs["masks"]) / Files.MASKS)
    summary.update(mask_route=masks_info.get("route"), mask_source=masks_info.get("source"))
    summary.update(method_param=p.method, method_item=ctx.item["method"], object=obj,
                   scene=ctx.item["scene"], train_views=len(scene.train),
                   views_with_mask=sum(m is not None for m in masks), extent=scene.extent)
    if sched is not None:
        eff = sched
        summary.update(delta=eff.threshold, scene_type=eff.scene_type, mask_stages=eff.num_mask_stages,
                       plan=eff.plan(), texture_adam=result.config.get("texture_adam"))
    write_json(ctx.out_dir / Files.REFINE, summary)
    ctx.log.info("%s: %d -> %d Gaussians, %d foreground, %.1f s", p.method, summary["num_gaussians_start"],
                 summary["num_gaussians_end"], summary["foreground"], timing["refine_s"])
    ctx.note(method=p.method, object=obj, num_gaussians_start=summary["num_gaussians_start"],
             num_gaussians_end=summary["num_gaussians_end"], foreground=summary["foreground"],
             splits=summary["splits"], pruned=summary["pruned"], ambiguous_final=summary["ambiguous_final"],
             **timing)
    return {"refined": ctx.out_dir}


def _key_params(params: RefineParams, full: dict) -> dict:
    """The params that enter the key: the method's own, as the method says
    (:meth:`cobgs.refine.methods.RefineMethod.key_params`: its name, the scene type, its
    sections; never another method's, so tuning FlashSplat's bias recomputes no COB-GS row)."""
    return method_for(params.method).key_params(full)


# version 7: the key holds only the method's own sections (every refine entry before it recomputes once)
STAGE = Stage(
    name="refine", version=7, run=_run, inputs=("dataset", "poses", "scene", "masks"), outputs=("refined",),
    params=RefineParams, key_params=_key_params, level=("scene", "method", "object"), uses_device=True,
    resources=Resources(cpus=2),
    description="COB-GS (or an ablation row / a peer) on one object: labels, splits, refined scene",
)
