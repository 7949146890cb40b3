"""Segmentation of a refined scene: extraction, PLY export and evaluation renders.

docs/method.md §2 "Segmentation" / "Evaluation render":

* foreground = label > 0.9, background = label < 0.1 (the complement used for object
  removal; Gaussians in between belong to neither);
* either part is exported as a standard 3DGS PLY (:func:`cobgs.gaussians.ply.save_ply`);
* the evaluation mask of a view keeps only the foreground Gaussians, renders their mask
  channel ``Σ mᵢ αᵢ Tᵢ`` (mᵢ = the method's ``mask_values``) and thresholds it at 0.5;
* RGB renders of the object alone and of the scene with the object removed.

Every function takes a :class:`cobgs.refine.result.RefineResult`, so COB-GS and the peers
are evaluated by the same code. Extraction (threshold + gather) is a single comparison
in logit space and one indexed copy per tensor.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch
from torch import Tensor

from cobgs.render.camera import Camera
from cobgs.data.scene import View
from cobgs.errors import InputError
from cobgs.gaussians.model import CORE, GaussianModel
from cobgs.evaluate.metrics import accuracy, boundary_iou, iou
from cobgs.refine.alternation import BG_THRESHOLD, FG_THRESHOLD, OBJECT_ID, OBJECT_LOGITS, MultiObjectResult
from cobgs.refine.result import RefineResult
from cobgs.refine.scores import LABEL

__all__ = [
    "label_sets",
    "subset",
    "extract",
    "export_ply",
    "export_objects",
    "object_index",
    "render_object_mask",
    "method_threshold",
    "render_object_rgb",
    "render_removed_rgb",
    "evaluate_masks",
    "visible_object_mask",
]


def _logit(p: float) -> float:
    return math.log(p / (1.0 - p))


def label_sets(
    logits: Tensor,  # [N]
    fg_threshold: float = FG_THRESHOLD,
    bg_threshold: float = BG_THRESHOLD,
) -> tuple[Tensor, Tensor]:
    """(foreground, background) [N] bool from label logits: sigmoid > fg / < bg threshold.

    The comparison is done on logits against logit(threshold) (monotone, exact, no
    sigmoid over N elements).
    """
    if not (0.0 < bg_threshold <= fg_threshold < 1.0):
        raise InputError(f"need 0 < bg_threshold <= fg_threshold < 1, got {bg_threshold}, {fg_threshold}")
    lg = logits.detach()
    return lg > _logit(fg_threshold), lg < _logit(bg_threshold)


def subset(model: GaussianModel, index: Tensor, extras: Optional[Sequence[str]] = None) -> GaussianModel:
    """A new model with the Gaussians ``index`` ([M] long or [N] bool): one gather per tensor.

    Args:
        model: the scene.
        index: which Gaussians.
        extras: extras to carry (default all).
    """
    if index.dtype == torch.bool:
        if index.shape != (len(model),):
            raise InputError(f"bool index must be [{len(model)}], got {list(index.shape)}")
        index = torch.nonzero(index, as_tuple=False)[:, 0]
    elif index.dtype not in (torch.int64, torch.int32) or index.dim() != 1:
        raise InputError(f"index must be a [M] long or [N] bool tensor, got {index.dtype} {list(index.shape)}")
    d = model.data
    out = GaussianModel(*(torch.index_select(d[k].detach(), 0, index) for k in CORE),
                        active_sh_degree=model.active_sh_degree)
    for name in model.extras if extras is None else extras:
        out.add_extra(name, torch.index_select(d[name].detach(), 0, index), fill=model.fill.get(name, 0))
    return out


def extract(result: RefineResult, part: str = "foreground", extras: Optional[Sequence[str]] = None) -> GaussianModel:
    """The object's Gaussians (``part="foreground"``) or the scene without the object
    (``"background"``) as a new model."""
    if part not in ("foreground", "background"):
        raise InputError(f'part must be "foreground" or "background", got {part!r}')
    return subset(result.model, getattr(result, part), extras)


def export_ply(
    result: RefineResult,
    out_dir: os.PathLike | str,
    stem: Optional[str] = None,
    extras: Sequence[str] = (),
) -> dict[str, Path]:
    """Write ``<stem>_object.ply`` and ``<stem>_background.ply`` (standard 3DGS layout).

    Args:
        result: a method's result.
        out_dir: destination folder (created).
        stem: file stem (default: the object name, else "object").
        extras: extra attributes to include (default none: a plain 3DGS file any viewer
            opens; e.g. ``("mask_logit",)`` to keep the labels).

    Returns:
        {"object": path, "background": path}.
    """
    from cobgs.gaussians.ply import save_ply

    out = Path(out_dir)
    stem = stem or result.object_name or "object"
    paths = {}
    for key, part in (("object", "foreground"), ("background", "background")):
        sub = extract(result, part, extras=list(extras))
        paths[key] = save_ply(out / f"{stem}_{key}.ply", sub, extras=list(extras))
    return paths


def object_index(multi: MultiObjectResult, name: str) -> Tensor:
    """[M] long indices of object ``name``'s Gaussians by the integer ``object_id``."""
    k = multi.index(name)
    return torch.nonzero(multi.model.data[OBJECT_ID] == k + 1, as_tuple=False)[:, 0]


def export_objects(multi: MultiObjectResult, out_dir: os.PathLike | str,
                   extras: Sequence[str] = ()) -> dict[str, Path]:
    """Per-object PLYs (label > 0.9 of each object) and the scene with every object
    removed (label < 0.1 for all objects), from one multi-object run.

    Returns:
        {object name: path, "_background": path}.
    """
    from cobgs.gaussians.ply import save_ply

    out = Path(out_dir)
    paths = {}
    logits = multi.model.data[OBJECT_LOGITS].detach()
    for k, name in enumerate(multi.object_names):
        fg, _ = label_sets(logits[:, k])
        paths[name] = save_ply(out / f"{_safe(name)}_object.ply", subset(multi.model, fg, list(extras)),
                               extras=list(extras))
    bg_all = (logits < _logit(BG_THRESHOLD)).all(dim=1)
    paths["_background"] = save_ply(out / "background.ply", subset(multi.model, bg_all, list(extras)),
                                    extras=list(extras))
    return paths


def _safe(name: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in name) or "object"


# -- evaluation renders -----------------------------------------------------------------------
def render_object_mask(
    result: RefineResult,
    camera: Camera,
    threshold: Optional[float] = None,
    backend: str = "native",
    soft: bool = False,
) -> Tensor:
    """The object's mask at ``camera``: foreground Gaussians only, mask channel, above
    ``threshold`` (None: the method's own bar, ``result.mask_threshold``, else 0.5 as
    docs/method.md §2).

    Returns:
        [H, W] bool (or the float mask channel when ``soft``).
    """
    from cobgs.render.rasterize import rasterize

    if result.mask_render != "object":
        return _scene_minmax_mask(result, camera, threshold, backend, soft)
    fg = torch.nonzero(result.foreground, as_tuple=False)[:, 0]
    cam = camera.to(result.model.device)
    if fg.numel() == 0:
        z = torch.zeros(cam.height, cam.width, device=result.model.device)
        return z if soft else z.bool()
    m = result.model
    with torch.no_grad():
        out = rasterize(m.means.detach()[fg], m.quats.detach()[fg], m.scales.detach()[fg],
                        m.opacities.detach()[fg], result.mask_values.detach()[fg][:, None].float(),
                        cam.viewmat, cam.K, int(cam.width), int(cam.height), backend=backend)
    mask = out.image[..., 0]
    return mask if soft else mask > method_threshold(result, threshold)


def _scene_minmax_mask(result: RefineResult, camera: Camera, threshold: Optional[float], backend: str,
                       soft: bool) -> Tensor:
    """LUDVIG's evaluation render (:mod:`cobgs.refine.ludvig`): every Gaussian with its value on
    a black background, min-max normalised over the image, above the bar (``threshold``, else
    the method's: ``1 - k / 100``, or Li's threshold of this render for "scene_minmax_li")."""
    from cobgs.refine.ludvig import SCENE_MINMAX, SCENE_MINMAX_LI, li_threshold, minmax
    from cobgs.render.image import render

    if result.mask_render not in (SCENE_MINMAX, SCENE_MINMAX_LI):
        raise InputError(f"unknown mask render {result.mask_render!r} of method {result.method!r} "
                         f"(expected 'object', {SCENE_MINMAX!r} or {SCENE_MINMAX_LI!r})")
    m = result.model
    with torch.no_grad():
        out = render(m, camera, None, features=result.mask_values.to(m.means.dtype)[:, None].contiguous(),
                     backend=backend)
    norm = minmax(out.image[..., 0])
    if soft:
        return norm
    if threshold is None and result.mask_render == SCENE_MINMAX_LI:
        return norm > li_threshold(norm)
    return norm > method_threshold(result, threshold)


def method_threshold(result: RefineResult, threshold: Optional[float] = None) -> float:
    """The bar of ``result``'s object render: ``threshold`` when given, else the method's
    own (``result.mask_threshold``), else 0.5."""
    if threshold is not None:
        return float(threshold)
    return 0.5 if result.mask_threshold is None else float(result.mask_threshold)


def _render_part(result: RefineResult, part: Tensor, camera: Camera, background, backend: str) -> Tensor:
    from cobgs.render.image import render

    sub = subset(result.model, part, extras=())
    with torch.no_grad():
        if len(sub) == 0:
            bg = torch.as_tensor(background if background is not None else (0.0, 0.0, 0.0), dtype=torch.float32)
            return bg.expand(camera.height, camera.width, 3).clone()
        return render(sub, camera, background, backend=backend).image


def render_object_rgb(result: RefineResult, camera: Camera, background=None, backend: str = "native") -> Tensor:
    """[H, W, 3] RGB of the object alone (foreground Gaussians)."""
    return _render_part(result, result.foreground, camera, background, backend)


def render_removed_rgb(result: RefineResult, camera: Camera, background=None, backend: str = "native") -> Tensor:
    """[H, W, 3] RGB of the scene with the object removed (background Gaussians)."""
    return _render_part(result, result.background, camera, background, backend)


def evaluate_masks(
    result: RefineResult,
    views: Sequence[View],
    gt_masks: Sequence[Optional[Tensor]],
    *,
    skip_empty_gt: bool = True,
    boundary_ratio: float = 0.02,
    backend: str = "native",
    visible: bool = False,
) -> dict:
    """IoU, accuracy and boundary IoU of the rendered object mask on held-out views.

    Args:
        result: a method's result.
        views: evaluation views.
        gt_masks: [H, W] bool GT per view (None = not annotated: skipped).
        skip_empty_gt: skip views whose GT is empty (object out of view), as the
            LERF-mask protocol does; counted in ``skipped``.
        boundary_ratio: boundary width ratio of the boundary IoU (docs/method.md §5).
        visible: predict the object's *visible* pixels
            (:func:`visible_object_mask`: every Gaussian rendered, the
            object's with their mask value, the others with 0, so occluders hide it) instead
            of the released object-only render (:func:`render_object_mask`, docs/method.md §2), which
            also predicts the parts another object hides. Use it whenever the GT masks are
            visible-pixel masks (synthetic scenes, NeRF-synthetic alpha): there the
            object-only render counts every occluded object pixel as a false positive.

    Returns:
        {"iou", "acc", "biou": means over the evaluated views (nan if none), "views":
        evaluated count, "skipped": list of skipped view names, "per_view": {name: {...}}}.
    """
    if len(gt_masks) != len(views):
        raise InputError(f"got {len(gt_masks)} GT masks for {len(views)} views")
    per, skipped = {}, []
    for v, gt in zip(views, gt_masks):
        if gt is None or (skip_empty_gt and not bool(gt.any())):
            skipped.append(v.name)
            continue
        if visible:
            pred = visible_object_mask(result, v.camera, backend=backend).cpu().numpy()
        else:
            pred = render_object_mask(result, v.camera, backend=backend).cpu().numpy()
        g = gt.cpu().numpy().astype(bool) if isinstance(gt, Tensor) else np.asarray(gt, bool)
        per[v.name] = {"iou": iou(pred, g), "acc": accuracy(pred, g), "biou": boundary_iou(pred, g, boundary_ratio)}
    out = {"views": len(per), "skipped": skipped, "per_view": per}
    for k in ("iou", "acc", "biou"):
        out[k] = float(np.mean([p[k] for p in per.values()])) if per else float("nan")
    return out


def visible_object_mask(result, camera, threshold=None, backend: str = "native", soft: bool = False):
    """The object's *visible* mask at ``camera`` (occlusion-aware): every Gaussian is
    rendered, the object's with their mask values and the others with 0, so what occludes
    the object in this view hides it (the occlusion-aware column of the evaluation).

    Args:
        result: a :class:`cobgs.refine.result.RefineResult` (any method).
        camera: the view.
        threshold: foreground where the blended mask value is above it (None: the
            method's own bar, :func:`method_threshold`; docs/method.md §2: 0.5).
        soft: return the blended mask value instead of the thresholded mask.

    Returns:
        [H, W] bool (or float32 when ``soft``).
    """
    import torch

    from cobgs.render.image import render

    if result.mask_render != "object":  # LUDVIG's evaluation is an in-scene render already
        return _scene_minmax_mask(result, camera, threshold, backend, soft)
    m = result.model
    vals = torch.where(result.foreground, result.mask_values.to(m.means.dtype), torch.zeros((), dtype=m.means.dtype,
                                                                                          device=m.device))
    with torch.no_grad():
        out = render(m, camera, None, features=vals[:, None].contiguous(), backend=backend)
    mask = out.image[..., 0]
    if soft:
        return mask
    return mask > method_threshold(result, threshold)
