"""The peers of docs/method.md §3, run in the same harness as COB-GS.

Every peer takes the same trained scene, training views and masks as :func:`cobgs.refine.alternation.refine`
and returns the same :class:`~cobgs.refine.result.RefineResult`, so
:func:`cobgs.refine.segment.evaluate_masks` and the exports treat all methods alike.

* **nosplit** — COB-GS's label optimisation without splitting (paper Table 5, first row):
  the same MASK stages, BAGS / BGTR / RAEM off.
* **sa3d** — SA3D-GS as its official ``sa3d-gs`` branch runs it: raw unbounded labels
  (init 0) blended as the mask channel, Adam lr 1.0, loss ``−Σ G·M + 0.3·Σ (1−G)·M`` (not
  normalised), two passes over the views in their fixed order. Pass 1 gates: from its
  second view on, a view whose mask rendered from the current labels (> 0.5) has IoU
  < 0.5 with its mask is skipped and remembered. Between the passes the Gaussians with
  label ≤ 0 leave the optimised set (background, no longer rendered; counted as
  ``dropped``, not pruned: they stay in the scene) — unless none is > 0, then all stay.
  Pass 2 tests nothing and skips exactly the views pass 1 skipped. Foreground = raw
  label > 0 (all of the set when none is); the object's render composites the raw
  labels, thresholded at 0.1 (``mask_threshold`` of the result, the evaluation's bar).
  :meth:`SA3DConfig.binary` renders the same segmentation with value 1 at 0.5;
  :meth:`SA3DConfig.strict` is the stricter variant (random order, no skipping, label
  > 0.5, mask value 1 thresholded at 0.5).
* **flashsplat** — FlashSplat: no optimisation. One forward pass per view accumulates,
  per Gaussian and GT label, ``Σ α·T`` over the pixels of that label; each Gaussian's
  vector is L2-normalised, the background bias ("slackness") is added to the background
  entry and the argmax decides (ties → background). A Gaussian never seen has a zero
  vector, so it goes to the background when the bias is ≥ 0 and to the object when it
  is < 0, as upstream. Multi-object: L1-normalise over the K + 1 labels and compare each
  object's share against the sum of the others (plus the bias); with a non-zero bias the
  [others, object] pair is L2-normalised first (upstream ``render.py``,
  ``multi_instance_opt``).

:func:`run_method` dispatches on a method name; it is the entry point of the pipeline's
refine stage (one call per scene, method and object).
"""

from __future__ import annotations

import dataclasses
import time
from typing import Mapping, Optional, Sequence

import torch
from torch import Tensor

from cobgs.data.scene import View
from cobgs.progress import Progress
from cobgs.configs import NOSPLIT_SWITCHES, FlashSplatConfig, RefineConfig, SA3DConfig
from cobgs.errors import InputError
from cobgs.gaussians.model import GaussianModel
from cobgs.refine.alternation import refine
from cobgs.refine.consistency import label_votes
from cobgs.refine.result import PeakMemory, RefineResult, StageStats
from cobgs.refine.scores import mask_loss, pixel_labels_from_mask, render_label_mask

__all__ = [
    "nosplit_config",
    "run_nosplit",
    "run_sa3d",
    "run_flashsplat",
    "run_flashsplat_multi",
    "flashsplat_votes",
]



def nosplit_config(base: RefineConfig = RefineConfig()) -> RefineConfig:
    """``base`` with BAGS, BGTR, RAEM, the object check and the object-share split off (paper Table 5, first row), training labels as
    long as the released labels-only run does: every stage of ``base``'s alternation becomes
    a mask stage (forward: 6 mask + 5 texture stages -> 11 mask stages = 22·V iterations;
    360°: 4 + 3 -> 7 = 14·V), not only the mask stages' share (docs/method.md §3)."""
    return dataclasses.replace(base, mask_stages=len(base.plan()), **NOSPLIT_SWITCHES)


def check_views_and_masks(views: Sequence[View], masks: Sequence) -> None:
    """At least one view, and one mask entry (a mask or None) per view."""
    if not views:
        raise InputError("need at least one training view")
    if len(masks) != len(views):
        raise InputError(f"got {len(masks)} masks for {len(views)} views (one per view, None = none)")


def run_nosplit(model: GaussianModel, views: Sequence[View], masks: Sequence[Optional[Tensor]], extent: float,
                config: RefineConfig = RefineConfig(), **kw) -> RefineResult:
    """Label optimisation without splitting: :func:`refine` with :func:`nosplit_config`."""
    kw.setdefault("method", "nosplit")
    return refine(model, views, masks, extent, nosplit_config(config), **kw)


def run_sa3d(
    model: GaussianModel,
    views: Sequence[View],
    masks: Sequence[Optional[Tensor]],
    config: SA3DConfig = SA3DConfig(),
    *,
    object_name: str = "",
    progress: "Progress" = True,
) -> RefineResult:
    """SA3D-GS on the scene ``model`` (not modified; see the module docstring)."""
    check_views_and_masks(views, masks)
    t0 = time.perf_counter()
    n = len(model)
    dev = model.device
    labels_px = [pixel_labels_from_mask(m, v.height, v.width, f"mask of view {v.name!r}").to(dev)
                 for m, v in zip(masks, views)]
    stats: list[StageStats] = []
    with PeakMemory() as mem:
        # The working set: a geometry-only copy plus the raw labels; pruning it keeps
        # Adam's moments aligned (GaussianModel.keep edits the optimizer too).
        work = GaussianModel(*(model.data[k].detach() for k in ("means", "log_scales", "quats", "opacity_logits",
                                                                  "sh0")),
                             torch.zeros(n, 0, 3, device=dev), active_sh_degree=0)
        work.add_extra("sa3d_label", torch.zeros(n, device=dev), fill=0.0)
        work.add_extra("source_index", torch.arange(n, device=dev), fill=-1)
        opt = work.make_adam({"sa3d_label": config.lr}, eps=config.adam_eps)
        rng = torch.Generator().manual_seed(config.seed)
        from cobgs.progress import make_bar

        bar = make_bar(progress, config.passes * len(views), f"sa3d {object_name}".strip())
        skip_set: set[int] = set()  # views the first pass skipped (by index)
        try:
            for p in range(config.passes):
                ts, losses, skipped = time.perf_counter(), [], 0
                order = (list(range(len(views))) if config.order == "fixed"
                         else torch.randperm(len(views), generator=rng).tolist())
                for step, i in enumerate(order):
                    out = None
                    if masks[i] is None:  # no annotation: nothing to train on (upstream has none)
                        skip = True
                    elif p == 0:
                        # Pass 1: the IoU gate, from the second view of the pass on.
                        skip = False
                        if step > 0 and config.skip_iou > 0:
                            out = render_label_mask(work, views[i].camera, work.data["sa3d_label"], None,
                                                    config.backend)
                            iou = _mask_iou(out.image[..., 0].detach() > config.gate_threshold, labels_px[i])
                            skip = iou < config.skip_iou  # nan (both empty) trains, as upstream's `IoU < t`
                    else:
                        # Later passes: no test, exactly the views pass 1 skipped.
                        skip = i in skip_set
                    if skip:
                        skipped += 1
                        if p == 0:
                            skip_set.add(i)
                        if bar is not None:
                            bar.update(1)
                        continue
                    if out is None:
                        out = render_label_mask(work, views[i].camera, work.data["sa3d_label"], None,
                                                config.backend)
                    loss = mask_loss(out.image[..., 0], labels_px[i], config.neg_weight, normalise=False)
                    loss.backward()
                    opt.step()
                    opt.zero_grad(set_to_none=True)
                    losses.append(float(loss.detach()))
                    if bar is not None:
                        bar.update(1)
                        bar.set_postfix(pass_=p, loss=f"{losses[-1]:.4g}", gaussians=len(work), skipped=skipped)
                dropped = 0
                if p == 0 and config.passes > 1:
                    keep = _segment(work.data["sa3d_label"].detach(), config)
                    dropped = int((~keep).sum())
                    work.keep(keep, [opt])
                stats.append(StageStats(kind="sa3d_pass", index=p, iterations=len(views) - skipped,
                                        gaussians_start=n, gaussians_end=n, dropped=dropped, skipped_views=skipped,
                                        mean_loss=sum(losses) / len(losses) if losses else float("nan"),
                                        wall_s=time.perf_counter() - ts))
        finally:
            if bar is not None:
                bar.close()
        fg = torch.zeros(n, dtype=torch.bool, device=dev)
        label = torch.full((n,), float("-inf"), device=dev)
        src = work.data["source_index"]
        final = work.data["sa3d_label"].detach()
        label[src] = final
        fg[src[_segment(final, config)]] = True
        out_model = model.clone()
        if "sa3d_label" in out_model.data:
            out_model.remove_extra("sa3d_label")
        # Gaussians dropped after the first pass keep −inf (they are background).
        out_model.add_extra("sa3d_label", label, fill=0.0)
    # The official evaluation render composites the raw labels; the strict variant renders
    # the foreground with mask value 1.
    values = (torch.where(fg, label, torch.zeros((), device=dev)) if config.render_values == "label"
              else torch.ones(n, device=dev))
    return RefineResult(method="sa3d", object_name=object_name, model=out_model, foreground=fg, background=~fg,
                        mask_values=values, stages=stats, num_gaussians_start=n, num_gaussians_end=n,
                        wall_s=time.perf_counter() - t0, peak_mem_bytes=mem.peak_bytes,
                        config=dataclasses.asdict(config), mask_threshold=config.render_threshold)


def _segment(label: Tensor, config: SA3DConfig) -> Tensor:
    """SA3D-GS's segmentation of the working set: raw label > ``label_threshold``, or
    every Gaussian when none passes and ``keep_all_if_none`` (upstream
    ``GaussianModel.segment``, used between the passes and by ``render.py --segment``)."""
    keep = label > config.label_threshold
    if config.keep_all_if_none and not bool(keep.any()):
        keep = torch.ones_like(keep)
    return keep


def _mask_iou(pred: Tensor, labels: Tensor) -> float:
    """IoU of a predicted [H, W] bool mask with pixel labels (1 object, 0 background,
    −1 ignored); nan when neither has a pixel."""
    valid = labels >= 0
    gt = labels == 1
    inter = int((pred & gt & valid).sum())
    union = int(((pred | gt) & valid).sum())
    return inter / union if union else float("nan")


def flashsplat_votes(model: GaussianModel, views: Sequence[View], pixel_labels: Sequence[Tensor], num_labels: int,
                     backend: str = "native") -> Tensor:
    """[N, num_labels] Σ α·T per GT label over all views (:func:`cobgs.refine.consistency.label_votes`)."""
    return label_votes(model, views, pixel_labels, num_labels, backend)


def run_flashsplat(
    model: GaussianModel,
    views: Sequence[View],
    masks: Sequence[Optional[Tensor]],
    config: FlashSplatConfig = FlashSplatConfig(),
    *,
    object_name: str = "",
    progress: "Progress" = False,
) -> RefineResult:
    """FlashSplat, one object (see the module docstring)."""
    check_views_and_masks(views, masks)
    t0 = time.perf_counter()
    n = len(model)
    with PeakMemory() as mem:
        labels_px = [pixel_labels_from_mask(mk, v.height, v.width, f"mask of view {v.name!r}")
                     for mk, v in zip(masks, views)]
        w = flashsplat_votes(model, views, labels_px, 2, config.backend)
        wn = w / w.norm(dim=1, keepdim=True).clamp_min(1e-12)
        # argmax over [background + bias, object]; ties (unseen with bias 0) → background.
        fg = wn[:, 1] > wn[:, 0] + config.background_bias
        out_model = model.clone()
        if "flashsplat_score" in out_model.data:
            out_model.remove_extra("flashsplat_score")
        out_model.add_extra("flashsplat_score", (wn[:, 1] - wn[:, 0]).float(), fill=0.0)
    wall = time.perf_counter() - t0
    st = StageStats(kind="flashsplat_vote", index=0, iterations=len(views), gaussians_start=n, gaussians_end=n,
                    wall_s=wall)
    return RefineResult(method="flashsplat", object_name=object_name, model=out_model, foreground=fg,
                        background=~fg, mask_values=torch.ones(n, device=fg.device), stages=[st],
                        num_gaussians_start=n, num_gaussians_end=n, wall_s=wall, peak_mem_bytes=mem.peak_bytes,
                        config=dataclasses.asdict(config))


def run_flashsplat_multi(
    model: GaussianModel,
    views: Sequence[View],
    masks: Mapping[str, Sequence[Optional[Tensor]]],
    config: FlashSplatConfig = FlashSplatConfig(),
) -> dict[str, RefineResult]:
    """FlashSplat for K objects at once (L1-normalised, each object vs the sum of the others).

    Pixel labels: 0 = background, k + 1 = object k; where masks overlap the later object
    wins; a view with no mask of any object (all None) is skipped. (A view missing only
    some objects' masks treats them as absent there.)

    Returns:
        object name → :class:`RefineResult` (sharing one scene copy).
    """
    names = list(masks)
    if not names:
        raise InputError("run_flashsplat_multi needs at least one object")
    for k in names:
        check_views_and_masks(views, masks[k])
    t0 = time.perf_counter()
    n, K = len(model), len(names)
    with PeakMemory() as mem:
        use_views, labels_px = [], []
        for i, v in enumerate(views):
            ms = [masks[k][i] for k in names]
            if all(m is None for m in ms):
                continue
            lab = torch.zeros(v.height, v.width, dtype=torch.int32)
            for k, m in enumerate(ms):
                if m is not None:
                    px = pixel_labels_from_mask(m, v.height, v.width, f"mask {names[k]!r} of view {v.name!r}")
                    lab[px == 1] = k + 1
            use_views.append(v)
            labels_px.append(lab)
        w = flashsplat_votes(model, use_views, labels_px, K + 1, config.backend)
        wn = w / w.sum(dim=1, keepdim=True).clamp_min(1e-12)
        out_model = model.clone()
        out_model.add_extra("flashsplat_share", wn[:, 1:].float(), fill=0.0)
    wall = time.perf_counter() - t0
    res = {}
    total = wn.sum(dim=1)
    for k, name in enumerate(names):
        share = wn[:, k + 1]
        others = total - share
        if config.background_bias != 0:
            # upstream render.py multi_instance_opt: with a slackness the [others, object]
            # pair is L2-normalised per Gaussian before the bias is added to "others".
            norm = torch.sqrt(others * others + share * share).clamp_min(1e-12)
            others, share = others / norm, share / norm
        fg = share > others + config.background_bias
        if not bool(wn[:, k + 1].any()):  # an object no view voted for gets nothing (upstream: skipped)
            fg = torch.zeros_like(fg)
        st = StageStats(kind="flashsplat_vote", index=0, iterations=len(use_views), gaussians_start=n,
                        gaussians_end=n, wall_s=wall)
        res[name] = RefineResult(method="flashsplat", object_name=name, model=out_model, foreground=fg,
                                 background=~fg, mask_values=torch.ones(n, device=fg.device), stages=[st],
                                 num_gaussians_start=n, num_gaussians_end=n, wall_s=wall,
                                 peak_mem_bytes=mem.peak_bytes,
                                 config=dataclasses.asdict(config) | {"objects": names})
    return res
