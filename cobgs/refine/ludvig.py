"""LUDVIG as its released code runs it on given masks (docs/method.md §3 "LUDVIG").

LUDVIG (Marrie et al., "LUDVIG: Learning-free Uplifting of 2D Visual features to Gaussian
Splatting scenes", ICCV 2025; code: naver/ludvig) trains nothing. Each Gaussian's feature is
the average of the 2D feature maps over every pixel it is blended into, weighted by its
rendering weight α·T there (``utils/solver.py`` ``uplifting``, the ``apply_weights`` CUDA
kernel). For a mask as the feature map that is

    f_i = Σ_views Σ_pixels m(p) α_i(p) T_i(p) / (Σ_views Σ_pixels α_i(p) T_i(p) + 1e-8),

i.e. the object's share of the Gaussian's Σ α·T (:func:`cobgs.refine.consistency.label_votes`
gives both sums in one forward pass per view). A scene of more than ``prune_min_gaussians``
Gaussians then loses those whose summed weight is at or below the ``prune_quantile`` quantile.
The release evaluates (``evaluation/spin_nvos``) by rendering ``f`` as the colour of the
whole scene on a black background, min-max normalising that render, and keeping the pixels
above ``1 - k / 100`` (k = 75 for SAM masks) or above Li's threshold (SAM2 masks). The
result carries that rule (``mask_render``), and :mod:`cobgs.refine.segment` renders it so.

What the release has that this harness does not run: its SAM route (SAM prompted with three
points sampled 10 times per view from the reference scribbles uplifted to 3D, the 10 masks
averaged) makes the masks; here the masks come from the workflow's mask route, like every
other method's. The DINOv2 features and the graph diffusion of ``dif_NVOS.yaml`` need DINOv2
weights and are not run.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Optional, Sequence

import torch
from torch import Tensor

from cobgs.configs import LUDVIGConfig
from cobgs.data.scene import View
from cobgs.errors import InputError
from cobgs.gaussians.model import GaussianModel
from cobgs.refine.consistency import label_votes
from cobgs.refine.peers import check_views_and_masks
from cobgs.refine.result import PeakMemory, RefineResult, StageStats
from cobgs.refine.scores import pixel_labels_from_mask

#: ``RefineResult.mask_render`` of LUDVIG's evaluation: the scene rendered with each Gaussian's
#: feature, min-max normalised, above the bar (fixed) or above Li's threshold of the render.
SCENE_MINMAX = "scene_minmax"
SCENE_MINMAX_LI = "scene_minmax_li"


def uplift_masks(model: GaussianModel, views: Sequence[View], masks: Sequence[Optional[Tensor]],
                 backend: str = "native") -> tuple[Tensor, Tensor]:
    """(features [N], weights [N]): each Gaussian's α·T-weighted mean of the masks, and its
    summed α·T over every pixel of every view with a mask (views without one are skipped)."""
    use, labels = [], []
    for v, m in zip(views, masks):
        if m is None:
            continue
        px = pixel_labels_from_mask(m, v.height, v.width, f"mask of view {v.name!r}")
        labels.append((px == 1).to(torch.int32))  # (a pixel the mask leaves out counts as 0, as upstream)
        use.append(v)
    if not use:
        raise InputError("LUDVIG needs at least one view with a mask")
    w = label_votes(model, use, labels, 2, backend)
    total = w.sum(dim=1)
    return (w[:, 1] / (total + 1e-8)).float(), total.float()


def minmax(x: Tensor) -> Tensor:
    """``(x - min) / (max - min)`` (all zeros where x is constant)."""
    lo, hi = x.min(), x.max()
    return (x - lo) / (hi - lo) if bool(hi > lo) else torch.zeros_like(x)


def li_threshold(x: Tensor) -> float:
    """Li's minimum cross-entropy threshold of the values (skimage ``threshold_li``)."""
    from skimage.filters import threshold_li

    return float(threshold_li(x.detach().cpu().numpy()))


def run_ludvig(
    model: GaussianModel,
    views: Sequence[View],
    masks: Sequence[Optional[Tensor]],
    config: LUDVIGConfig = LUDVIGConfig(),
    *,
    object_name: str = "",
    progress=False,
) -> RefineResult:
    """LUDVIG on one object (module docstring). The result's ``model`` is the scene after the
    pruning (the input scene when it holds no more than ``prune_min_gaussians``), with the
    feature as the extra ``ludvig_feature``; ``mask_values`` is the feature; ``foreground`` is
    the Gaussians whose min-max normalised feature passes the evaluation's bar (the release
    has no Gaussian set of its own: its removal renders drop those below it)."""
    check_views_and_masks(views, masks)
    t0 = time.perf_counter()
    n = len(model)
    with PeakMemory() as mem:
        feat, weight = uplift_masks(model, views, masks, config.backend)
        out_model = model.clone()
        if n > config.prune_min_gaussians:
            keep = weight > torch.quantile(weight.double(), config.prune_quantile).to(weight.dtype)
            out_model.keep(keep)
            feat = feat[keep]
        if "ludvig_feature" in out_model.data:
            out_model.remove_extra("ludvig_feature")
        out_model.add_extra("ludvig_feature", feat, fill=0.0)
        norm = minmax(feat)
        if config.thresholding == "li":
            bar, render_rule, threshold = li_threshold(norm), SCENE_MINMAX_LI, None
        else:
            bar = 1.0 - config.threshold_k / 100.0
            render_rule, threshold = SCENE_MINMAX, bar
        fg = norm > bar
    wall = time.perf_counter() - t0
    st = StageStats(kind="ludvig_uplift", index=0, iterations=sum(m is not None for m in masks),
                    gaussians_start=n, gaussians_end=len(out_model), pruned=n - len(out_model), wall_s=wall)
    return RefineResult(method="ludvig", object_name=object_name, model=out_model, foreground=fg, background=~fg,
                        mask_values=feat, stages=[st], num_gaussians_start=n, num_gaussians_end=len(out_model),
                        wall_s=wall, peak_mem_bytes=mem.peak_bytes, config=dataclasses.asdict(config),
                        mask_threshold=threshold, mask_render=render_rule)
