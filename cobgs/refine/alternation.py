"""COB-GS refinement (docs/method.md §2): alternating MASK / TEXTURE stages with boundary splits.

The schedule, with V training views and stages of 2V iterations::

    MASK, TEXTURE, MASK, TEXTURE, ..., MASK          forward-facing: 6 + 5 stages = 22 V
                                                      360°:           4 + 3 stages = 14 V

* **MASK stage** — only the label logits train (Adam, lr 0.1, eps 1e-15) on the
  normalised mask loss; the rendered mask reaches the labels only
  (:mod:`cobgs.refine.scores`). Every iteration adds the view's per-Gaussian score
  ``|N⁺ − N⁻| / (N⁺ + N⁻ + 1e-6)`` (unseen = 1) to the stage accumulator. At the end of
  the stage the Gaussians whose mean score is < δ are ambiguous; the large ones are split
  (BAGS, :mod:`cobgs.refine.split`) and the accumulator is reset.
* **TEXTURE stage** — labels frozen; every other tensor trains on 0.8·L1 + 0.2·(1−SSIM)
  with the 3DGS learning rates (:class:`cobgs.train.optimize.TrainConfig` defaults), except the
  position lr, fixed at its final value 1.6e-6 × extent; no densification, no opacity
  reset.
* **Last MASK stage** — ends with RAEM instead of a split, as in the released code (its
  final iteration calls ``mask_and_split(..., prune_only=True)``): a split there would
  leave children with label 0.5 that no later stage trains. With RAEM "off" it ends with
  neither.

Label learning rate and stage length: Adam moves a logit by at most about lr per step,
so a label needs ≳ ln 9 / 0.1 ≈ 22 steps from 0 to pass the 0.9 foreground threshold; a
stage of 2V iterations allows that only when V ≳ 11. Children of the last split (reset to
label 0.5) get exactly one MASK stage, so scenes with very few views leave them unlabelled
unless ``stage_length_views`` is raised.

The texture optimizer continues the baseline's Adam, as the released code does (it
restores the 3DGS checkpoint's optimizer state): pass the moments training exported
(:attr:`cobgs.train.optimize.TrainResult.adam_moments`, or the ``adam_moments.pt`` the pipeline
writes next to ``scene.ply``; :mod:`cobgs.train.adam_moments`) as ``texture_moments``. Without
them (a bare PLY) the texture stages start from zero moments, whose first bias-corrected
steps move every parameter in view by about its learning rate; the run says so (a log
warning and ``config["texture_adam"] == "fresh"``) and segments measurably worse (on the
coarse synthetic orbit scene: mean boundary IoU 90.1 vs 93.1 with the baseline's moments).
``RefineConfig(texture_adam="fresh")`` asks for zero moments on purpose (ablation).

Views are drawn at random without replacement, the queue refilled every V iterations;
all randomness comes from private generators seeded by ``RefineConfig.seed``. Both Adam
optimizers (labels, texture) live for the whole run and are edited with the model at
every split / prune, so their moments stay aligned with the Gaussians.

Multi-object (:func:`refine_objects`): objects are refined one after another on the
updated scene, each with fresh labels; then one label-only MASK stage per object
(except the last, whose labels are already final on this scene) gives each object's
labels on the final scene, stored as the [N, K] extra ``object_logits`` plus an integer
``object_id`` (0 = none, k + 1 = object k) for fast lookup.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass, field
from typing import Callable, Mapping, Optional, Sequence

import torch
from torch import Tensor

from cobgs.progress import Progress
from cobgs.train.adam_moments import Moments, export_moments, load_moments
from cobgs.data.scene import Scene, View
from cobgs.errors import InputError
from cobgs.gaussians.model import GaussianModel, gaussian_lrs
from cobgs.train.losses import photometric_loss
from cobgs.refine.result import PeakMemory, RefineResult, StageStats
from cobgs.refine.consistency import drawn_agreement, label_votes, object_render_check, undecided_by_votes
from cobgs.refine.scores import (
    ScoreAccumulator,
    object_share,
    ensure_label,
    mask_loss,
    pixel_labels_from_mask,
    render_label_mask,
    view_scores,
)
from cobgs.refine.split import boundary_split, raem_prune_mask, split_candidates
from cobgs.render.image import render
from cobgs.memory import retain_freed_memory
from cobgs.configs import CHECKED, FOREGROUND_LABEL, NGSConfig, RefineConfig

__all__ = [
    "Refiner",
    "refine",
    "refine_scene",
    "refine_objects",
    "apply_raem",
    "final_sets",
    "MultiObjectResult",
    "masks_for",
    "FG_THRESHOLD",
    "BG_THRESHOLD",
]

FG_THRESHOLD = FOREGROUND_LABEL  # docs/method.md §2 segmentation: foreground = label > 0.9
BG_THRESHOLD = 0.1  # background = label < 0.1
OBJECT_LOGITS = "object_logits"
OBJECT_ID = "object_id"

log = logging.getLogger(__name__)


def masks_for(views: Sequence[View], object_name: str) -> list[Optional[Tensor]]:
    """The object's mask in each view (None where the view has no annotation of it)."""
    return [v.masks.get(object_name) for v in views]


class Refiner:
    """The state of one COB-GS refinement; :func:`refine` drives it.

    Args:
        model: the scene, edited in place (pass a clone to keep the original).
        views: training views (camera and image).
        masks: one GT mask per view (see :func:`cobgs.refine.scores.pixel_labels_from_mask`:
            [H, W] bool, or int with −1 = don't care, or None = not annotated).
        extent: scene extent (world units).
        config: the parameters.
        background: RGB behind the scene in TEXTURE stages (the baseline's).
        reset_labels: start every label logit at 0 (docs/method.md §2).
        texture_moments: the baseline's Adam moments of the texture tensors
            (:mod:`cobgs.train.adam_moments`); used when ``config.texture_adam == "baseline"``.
        ngs: NG-GS's boundary stage (:mod:`cobgs.refine.ngs`): its loss joins every TEXTURE
            iteration's; None (COB-GS) leaves the texture step as it is.

    Attributes:
        texture_adam: "baseline" when the texture Adam started from ``texture_moments``,
            "fresh" when it started from zero moments.
    """

    def __init__(
        self,
        model: GaussianModel,
        views: Sequence[View],
        masks: Sequence[Optional[Tensor]],
        extent: float,
        config: RefineConfig = RefineConfig(),
        background: Sequence[float] = (0.0, 0.0, 0.0),
        reset_labels: bool = True,
        texture_moments: Optional[Moments] = None,
        ngs: Optional[NGSConfig] = None,
    ):
        if not views:
            raise InputError("refinement needs at least one training view")
        if len(masks) != len(views):
            raise InputError(f"got {len(masks)} masks for {len(views)} views (one per view, None = none)")
        if not (isinstance(extent, (int, float)) and math.isfinite(extent) and extent > 0):
            raise InputError(f"extent must be a positive number, got {extent!r}")
        retain_freed_memory()  # process-wide: see cobgs/memory.py
        self.model = model
        self.views = list(views)
        self.config = c = config
        self.extent = float(extent)
        self.background = torch.as_tensor(background, dtype=torch.float32).reshape(3)
        self.pixel_labels = [pixel_labels_from_mask(m, v.height, v.width, f"mask of view {v.name!r}").to(model.device)
                             for m, v in zip(masks, self.views)]
        if all(bool((p < 0).all()) for p in self.pixel_labels):
            raise InputError("no view has an annotated mask pixel for this object")
        ensure_label(model, c.label_name, reset=reset_labels)
        self.label_opt = model.make_adam({c.label_name: c.label_lr}, eps=c.adam_eps)
        self.texture_opt = model.make_adam(gaussian_lrs(c, c.position_lr, self.extent), eps=c.adam_eps)
        self.texture_adam = "fresh"
        if c.texture_adam == "baseline" and texture_moments is not None:
            load_moments(self.texture_opt, texture_moments, "texture_moments")
            self.texture_adam = "baseline"
        self.view_rng = torch.Generator().manual_seed(c.seed)
        self.split_rng = torch.Generator().manual_seed(c.seed + 1)
        self.queue: list[int] = []
        self.scores = ScoreAccumulator(len(model), model.device)
        # the object's view of ambiguity (``RefineConfig.split_object_share``): each Gaussian's
        # minority Σ α·T as a share of the object's Σ α·T in the view, summed over the stage
        self.object_share = ScoreAccumulator(len(model), model.device) if c.split_object_share > 0 else None
        # what RAEM removed at the end (None while nothing was): the scene before it
        self.raem_keep: Optional[Tensor] = None
        self.raem_removed: Optional[GaussianModel] = None
        # RefineConfig.raem_object_by_masks: (as published, with the object spared), RAEM's two
        # prune masks where they differ; refine() applies one after the run
        self.raem_choice: Optional[tuple[Tensor, Tensor]] = None
        self.iteration = 0
        self.last_mask_info: dict = {}
        self.ngs = None
        if ngs is not None:
            from cobgs.refine.ngs import NGSStage

            self.ngs = NGSStage(ngs, model.device)

    @property
    def optimizers(self) -> list:
        return [self.label_opt, self.texture_opt]

    def next_view(self) -> int:
        """Index of the next view: random without replacement, refilled every V draws."""
        if not self.queue:
            self.queue = torch.randperm(len(self.views), generator=self.view_rng).tolist()
        return self.queue.pop()

    # -- iterations --------------------------------------------------------------------------
    def mask_step(self, i: int) -> float:
        """One MASK iteration on view ``i``: label loss, scores, label update."""
        c, view = self.config, self.views[i]
        logits = self.model.data[c.label_name]
        out = render_label_mask(self.model, view.camera, torch.sigmoid(logits), self.pixel_labels[i], c.backend)
        loss = mask_loss(out.image[..., 0], self.pixel_labels[i], c.mask_lambda)
        loss.backward()
        with torch.no_grad():
            self.scores.add(view_scores(out.label_counts, out.label_weights, c.score == "weight", c.mask_lambda))
            if self.object_share is not None:
                self.object_share.add(object_share(out.label_weights))
            self.label_opt.step()
            self.label_opt.zero_grad(set_to_none=True)
        self.iteration += 1
        return float(loss.detach())

    def texture_step(self, i: int) -> float:
        """One TEXTURE iteration on view ``i``: photometric loss, geometry/colour update."""
        c, view = self.config, self.views[i]
        out = render(self.model, view.camera, self.background, backend=c.backend)
        loss = photometric_loss(out.image, view.image.to(out.image.device), c.ssim_weight)
        if self.ngs is not None:  # (the accumulator is empty in texture stages, as NG-GS's after a split)
            loss = loss + self.ngs.loss(self.model, c.label_name, self.scores.sum)
        loss.backward()
        with torch.no_grad():
            self.texture_opt.step()
            self.texture_opt.zero_grad(set_to_none=True)
            if self.ngs is not None:
                self.ngs.step()
        self.iteration += 1
        return float(loss.detach())

    # -- stage ends --------------------------------------------------------------------------
    def end_mask_stage(self, length: int, last: bool) -> dict:
        """Classify, then split (or, after the last stage, apply RAEM); reset the scores.

        Returns:
            ``ambiguous``, ``ambiguous_large``, ``split``, ``pruned`` counts and the
            stage-mean ``scores`` [N] (before the edit).
        """
        c, m = self.config, self.model
        mean = self.scores.mean(length)
        amb = mean < c.threshold
        info = {"ambiguous": int(amb.sum()), "split": 0, "pruned": 0, "scores": mean}
        to_split = amb
        if self.object_share is not None:  # split (never pruned): what costs the object ≥ the share
            wide = (self.object_share.mean(length) >= c.split_object_share) & ~amb
            info["object_share"] = int(wide.sum())
            to_split = amb | wide
        large = split_candidates(m, to_split, self.extent, c.split_size_fraction)
        info["ambiguous_large"] = int(large.sum())
        if last:
            # the labels' object, which raem_spare_object never prunes (the check judges those)
            # and raem_object_by_masks weighs against pruning
            labelled = label_sets(m.data[c.label_name])[0] if c.raem_spare_object or c.raem_object_by_masks else None
            cams = [v.camera for v in self.views]
            prune = raem_prune_mask(m, amb, c.raem, cams, c.raem_footprint_px, labelled if c.raem_spare_object else None)
            info["pruned"] = int(prune.sum())
            if c.raem_object_by_masks:  # refine() chooses, once the check can judge both outcomes
                spared = raem_prune_mask(m, amb, c.raem, cams, c.raem_footprint_px, labelled)
                if not torch.equal(spared, prune):
                    self.raem_choice = (prune, spared)
                    prune = torch.zeros_like(prune)
            if bool(prune.any()):
                self.raem_keep, self.raem_removed = ~prune, m.select(prune)
                m.keep(~prune, self.optimizers)
        elif c.bags:
            info["split"] = boundary_split(
                m, to_split, self.extent, size_fraction=c.split_size_fraction, n_children=c.split_children,
                scale_divisor=c.split_scale_divisor, reset=(c.label_name,), optimizers=self.optimizers,
                generator=self.split_rng,
            )
        self.scores.reset(len(m))
        if self.object_share is not None:
            self.object_share.reset(len(m))
        self.last_mask_info = info  # (for diagnostics: Refiner.run's on_stage_end)
        return info

    # -- the whole run -----------------------------------------------------------------------
    def run(self, progress=True, desc: str = "refine",
            on_stage_end: Optional["Callable[[Refiner, StageStats], None]"] = None,
            on_stage_start: Optional["Callable[[Refiner, int, str], None]"] = None,
            ) -> tuple[list[StageStats], list[Tensor], int]:
        """Run every stage of ``config.plan()``.

        ``on_stage_start(refiner, index, kind)`` and ``on_stage_end(refiner, stats)`` are
        called around every stage (after its split / RAEM): diagnostics read the model,
        labels and scores there (``tests/benchmarks/bm_refine_trajectory.py``); they must not
        edit them.

        Returns:
            (stage statistics, stage-mean scores of each mask stage, ambiguous count at
            the end before RAEM).
        """
        c = self.config
        plan = c.plan()
        length = c.stage_length(len(self.views))
        from cobgs.progress import make_bar

        bar = make_bar(progress, len(plan) * length, desc)
        stats: list[StageStats] = []
        scores: list[Tensor] = []
        ambiguous_final = -1
        last_amb = -1
        n_mask_done = 0
        try:
            for si, kind in enumerate(plan):
                if on_stage_start is not None:
                    on_stage_start(self, si, kind)
                t0 = time.perf_counter()
                n0 = len(self.model)
                losses = []
                for _ in range(length):
                    i = self.next_view()
                    loss = self.mask_step(i) if kind == "mask" else self.texture_step(i)
                    losses.append(loss)
                    if bar is not None:
                        bar.update(1)
                        if len(losses) % 10 == 0 or len(losses) == length:
                            bar.set_postfix(stage=f"{kind}{si}", it=self.iteration, loss=f"{loss:.4g}",
                                            gaussians=len(self.model), ambiguous=last_amb)
                st = StageStats(kind=kind, index=si, iterations=length, gaussians_start=n0, gaussians_end=n0,
                                mean_loss=sum(losses) / len(losses))
                if kind == "mask":
                    n_mask_done += 1
                    last = n_mask_done == c.num_mask_stages
                    info = self.end_mask_stage(length, last)
                    st.ambiguous, st.ambiguous_large = info["ambiguous"], info["ambiguous_large"]
                    st.split, st.pruned = info["split"], info["pruned"]
                    last_amb = info["ambiguous"]
                    if c.record_scores:
                        scores.append(info["scores"])
                    if last:
                        ambiguous_final = info["ambiguous"]
                st.gaussians_end = len(self.model)
                st.wall_s = time.perf_counter() - t0
                _check_refined(self.model, c.label_name, f"{desc}: stage {si} ({kind}), iteration {self.iteration}")
                if on_stage_end is not None:
                    on_stage_end(self, st)
                stats.append(st)
                if bar is not None:
                    bar.set_postfix(stage=f"{kind}{si}", it=self.iteration, gaussians=len(self.model), ambiguous=last_amb)
        finally:
            if bar is not None:
                bar.close()
        return stats, scores, ambiguous_final


def _check_refined(model: GaussianModel, label: str, where: str) -> None:
    """Stop a refinement whose labels or parameters became non-finite (never a result)."""
    from cobgs.errors import DivergenceError
    from cobgs.train.optimize import check_model_finite

    check_model_finite(model, where)
    lg = model.data.get(label)
    if lg is not None and not bool(torch.isfinite(lg.detach()).all()):
        raise DivergenceError(f"{where}: non-finite label logits; nothing is saved")


def short_stage_warning(config: RefineConfig, num_views: int) -> Optional[str]:
    """Why a splitting schedule cannot finish its labels, or None: with stages of
    ``stage_length_views × V`` iterations shorter than
    :meth:`RefineConfig.steps_to_foreground`, no
    label passes 0.9 in the first MASK stage and the children of the last split (label 0.5
    again, one MASK stage left) never become foreground, so the object comes out with
    holes along its boundary (measured on the 9-view LERF-mask fixture:
    docs/benchmarks/protocol_workflows.md)."""
    if not config.stages_too_short(num_views):
        return None
    length, need = config.stage_length(num_views), config.steps_to_foreground()
    return (f"stages of {length} iterations ({config.stage_length_views:g} x {num_views} views) are "
            f"shorter than the {need} a label needs to pass 0.9 from 0.5 at label_lr {config.label_lr:g}: "
            f"boundary Gaussians split in the last stages cannot become foreground; set "
            f"refine.cobgs.stage_length_views >= {config.min_stage_length_views(num_views):g} (or raise label_lr)")


def label_sets(logits: Tensor) -> tuple[Tensor, Tensor]:
    """(foreground, background) [N] bool of label logits: sigmoid > 0.9 / < 0.1.

    Compared in logit space (logit(0.9) = ln 9), which is exact and avoids a sigmoid.
    """
    t_fg = math.log(FG_THRESHOLD / (1.0 - FG_THRESHOLD))
    t_bg = math.log(BG_THRESHOLD / (1.0 - BG_THRESHOLD))
    lg = logits.detach()
    return lg > t_fg, lg < t_bg


def refine(
    model: GaussianModel,
    views: Sequence[View],
    masks: Sequence[Optional[Tensor]],
    extent: float,
    config: RefineConfig = RefineConfig(),
    *,
    background: Sequence[float] = (0.0, 0.0, 0.0),
    object_name: str = "",
    method: str = "cobgs",
    progress: "Progress" = True,
    copy: bool = True,
    texture_moments: Optional[Moments] = None,
    return_moments: bool = False,
    ngs: Optional[NGSConfig] = None,
) -> RefineResult:
    """Refine ``model`` for one object with COB-GS and segment it.

    Args:
        model: the trained 3DGS scene (left untouched when ``copy``).
        views: training views.
        masks: the object's GT mask per view ([H, W] bool / int with −1 = ignore / None).
        extent: scene extent.
        config: the parameters (ablation switches included).
        background: the baseline's background colour (TEXTURE stages render on it).
        object_name: recorded in the result.
        method: recorded in the result ("cobgs", or an ablation row's name).
        progress: False, True (a tqdm bar) or a factory (:mod:`cobgs.progress`); shows the
            stage, iteration, loss, Gaussians and ambiguous count.
        copy: refine a clone of ``model`` (True) or ``model`` itself.
        texture_moments: the baseline's Adam moments (:mod:`cobgs.train.adam_moments`) for the
            TEXTURE stages; without them those stages start from zero moments (logged).
        return_moments: keep the texture Adam's final moments in the result (to continue
            from them, as :func:`refine_objects` does for the next object).
        ngs: NG-GS's boundary stage in the TEXTURE iterations (:mod:`cobgs.refine.ngs`);
            None: COB-GS as it is.

    Returns:
        :class:`RefineResult`; ``model`` carries the label-logit extra; foreground =
        label > 0.9, background = label < 0.1, mask values = labels;
        ``config["texture_adam"]`` says how the texture Adam started.
    """
    m = model.clone() if copy else model
    n0 = len(m)
    t0 = time.perf_counter()
    with PeakMemory() as mem:
        r = Refiner(m, views, masks, extent, config, background, texture_moments=texture_moments, ngs=ngs)
        if config.bgtr and config.texture_adam == "baseline" and r.texture_adam == "fresh":
            log.warning("%s %s: no baseline Adam moments given; the TEXTURE stages start from zero moments "
                        "(pass texture_moments, e.g. TrainResult.adam_moments or read_moments(adam_moments.pt))",
                        method, object_name)
        short = short_stage_warning(config, len(r.views))
        if short:
            log.warning("%s %s: %s", method, object_name, short)
        stats, scores, amb = r.run(progress=progress, desc=f"{method} {object_name}".strip())
        raem_choice = None
        if r.raem_choice is not None:  # RefineConfig.raem_object_by_masks (it has the final sets)
            raem_choice, (fg, bg, in_scene, checked) = _prune_by_masks(m, r, config, stats[-1])
        else:
            fg, bg, in_scene, checked = final_sets(m, r.views, r.pixel_labels, config)
        logits = m.data[config.label_name]
    wall = time.perf_counter() - t0
    return RefineResult(
        method=method,
        object_name=object_name,
        model=m,
        foreground=fg,
        background=bg,
        mask_values=torch.sigmoid(logits.detach()),
        foreground_in_scene=in_scene,
        stages=stats,
        stage_scores=scores,
        ambiguous_final=amb,
        num_gaussians_start=n0,
        num_gaussians_end=len(m),
        wall_s=wall,
        peak_mem_bytes=mem.peak_bytes,
        config=dict(config.as_dict(), texture_adam=r.texture_adam, object_check_dropped=checked,
                    **({"raem_object_chose": raem_choice} if raem_choice is not None else {}),
                    **({"ngs": dataclasses.asdict(ngs)} if ngs is not None else {})),
        texture_moments=export_moments(r.texture_opt) if return_moments else None,
        raem_keep=r.raem_keep,
        raem_removed=r.raem_removed,
    )


def _prune_by_masks(model: GaussianModel, r: "Refiner", config: RefineConfig, last_stage) -> tuple[str, tuple]:
    """RefineConfig.raem_object_by_masks: of RAEM's two prune masks (``r.raem_choice``: as
    published, and sparing what the labels call object), apply the one whose object alone, after
    the final sets (the check), agrees better with the training masks
    (:func:`cobgs.refine.consistency.drawn_agreement`; a tie keeps RAEM as published). Records it
    on the Refiner and the last stage as a prune in that stage would. Returns "paper" or "spare",
    and the chosen outcome's :func:`final_sets` (those of ``model`` as it is left)."""
    published, spared = r.raem_choice
    outcomes = []
    for prune in (published, spared):
        rest = model.select(~prune)  # (the order keep() leaves: the final sets hold for the model)
        sets = final_sets(rest, r.views, r.pixel_labels, config)
        outcomes.append((drawn_agreement(rest, sets[0], r.views, r.pixel_labels, config.backend), sets))
    chose = "spare" if outcomes[1][0] > outcomes[0][0] else "paper"
    prune, sets = (spared, outcomes[1][1]) if chose == "spare" else (published, outcomes[0][1])
    if bool(prune.any()):
        r.raem_keep, r.raem_removed = ~prune, model.select(prune)
        model.keep(~prune, r.optimizers)
    last_stage.pruned, last_stage.gaussians_end = int(prune.sum()), len(model)
    return chose, sets


def refine_scene(model: GaussianModel, scene: Scene, object_name: str, config: RefineConfig = RefineConfig(),
                 **kw) -> RefineResult:
    """:func:`refine` with the training views, masks, extent and background of ``scene``."""
    if object_name not in scene.object_names:
        raise InputError(f"object {object_name!r} has no masks in this scene (objects: {scene.object_names})")
    return refine(model, scene.train, masks_for(scene.train, object_name), scene.extent, config,
                  background=scene.background, object_name=object_name, **kw)


def final_sets(model: GaussianModel, views: Sequence[View], pixel_labels: Sequence[Tensor],
               config: RefineConfig) -> tuple[Tensor, Tensor, Optional[Tensor], int]:
    """What a refined scene's labels give, as :func:`refine` returns it: ``(foreground,
    background, foreground_in_scene, dropped)``.

    The labels' verdict (label > 0.9 / < 0.1), then, as ``config`` asks, the object-render
    check (``object_check``: the foreground for the object alone, ``dropped`` Gaussians fewer)
    and, per use, the object within the scene: the labels' verdict, plus the undecided
    Gaussians the training masks' votes call object (``in_scene_undecided = "votes"``).
    ``pixel_labels``: one per view, as :func:`cobgs.refine.scores.pixel_labels_from_mask`.
    """
    logits = model.data[config.label_name]
    fg, bg = label_sets(logits)
    if config.object_check not in CHECKED:
        return fg, bg, None, 0
    kept = object_render_check(model, fg, views, pixel_labels, config.mask_lambda, config.backend,
                               edge_px=config.object_check_edge_px, rule=config.object_check_rule)
    in_scene = None
    if config.object_check == "per_use":  # the object within the scene: the labels' verdict ...
        in_scene = fg
        if config.in_scene_undecided == "votes":  # ... and the undecided ones the votes call object
            votes = label_votes(model, views, pixel_labels, 2, config.backend)
            in_scene = fg | undecided_by_votes(torch.sigmoid(logits.detach()), votes, config.mask_lambda,
                                               BG_THRESHOLD, FG_THRESHOLD)
    return kept, bg, in_scene, int((fg & ~kept).sum())


def apply_raem(
    result: RefineResult,
    variant: str,
    views: Sequence[View] = (),
    footprint_px: Optional[float] = None,
    method: Optional[str] = None,
    spare: Optional[Tensor] = None,
) -> RefineResult:
    """RAEM applied after a run made with ``raem="off"``: the same result as running with
    ``raem=variant`` (pruning is the last edit and changes no label), without rerunning.

    Lets one refinement give the RAEM ablation rows (off / released / paper), and measure a
    pruning rule on cached refinements (``spare``).

    Args:
        result: a COB-GS result with ``config["raem"] == "off"`` and recorded scores.
        variant: "off", "released" or "paper".
        views: training views (cameras for "paper").
        footprint_px: the "paper" threshold (default: the run's ``raem_footprint_px``).
        method: label of the new result (default: the input's).
        spare: [N] bool, Gaussians never pruned whatever the variant says (None: none).

    Returns:
        a new :class:`RefineResult` (the input is not modified).
    """
    cfg = result.config
    if cfg.get("raem") != "off" or not result.stage_scores:
        raise InputError('apply_raem needs a result of a run with raem="off" and record_scores=True')
    scores = result.stage_scores[-1]
    if scores.shape[0] != len(result.model):
        raise InputError("the last stage's scores do not match the model (was it edited after the run?)")
    amb = scores < cfg["threshold"]
    fp = cfg["raem_footprint_px"] if footprint_px is None else footprint_px
    t0 = time.perf_counter()
    prune = raem_prune_mask(result.model, amb, variant, [v.camera for v in views], fp, spare)
    m = result.model.clone()
    removed = m.select(prune) if bool(prune.any()) else None
    m.keep(~prune)
    logits = m.data[cfg["label_name"]]
    fg, bg = label_sets(logits)
    stages = [dataclasses.replace(s) for s in result.stages]
    if stages:  # (a result read back from a refine entry has no stage records)
        stages[-1].pruned = int(prune.sum())
        stages[-1].gaussians_end = len(m)
    return dataclasses.replace(
        result, method=method or result.method, model=m, foreground=fg, background=bg,
        mask_values=torch.sigmoid(logits.detach()), stages=stages, num_gaussians_end=len(m),
        wall_s=result.wall_s + time.perf_counter() - t0,
        config=dict(cfg, raem=variant, raem_footprint_px=fp),
        raem_keep=None if removed is None else ~prune,
        raem_removed=removed,
    )


# -- multi-object ---------------------------------------------------------------------------
@dataclass
class MultiObjectResult:
    """K objects refined sequentially on one scene (docs/method.md §2 multi-object).

    Attributes:
        model: the final scene, with extras ``object_logits`` [N, K] (each object's label
            logit from the final label pass) and ``object_id`` [N] int64 (0 = no object,
            k + 1 = the object with the highest label among those above 0.9).
        object_names: the K objects, in refinement order.
        refinements: each object's sequential refinement summary (:meth:`RefineResult.summary`).
        final_pass: the label-only stage of each object on the final scene (None for the
            last object, whose labels are already final).
        wall_s: total wall time.
        peak_mem_bytes: peak RSS above the start.
    """

    model: GaussianModel
    object_names: list[str]
    refinements: list[dict] = field(default_factory=list)
    final_pass: list[Optional[StageStats]] = field(default_factory=list)
    wall_s: float = 0.0
    peak_mem_bytes: int = 0

    def index(self, name: str) -> int:
        if name not in self.object_names:
            raise InputError(f"unknown object {name!r} (objects: {self.object_names})")
        return self.object_names.index(name)

    def result(self, name: str, method: str = "cobgs") -> RefineResult:
        """The single-object view of object ``name`` on the final scene (shares ``model``)."""
        k = self.index(name)
        logits = self.model.data[OBJECT_LOGITS][:, k].detach()
        fg, bg = label_sets(logits)
        s = self.refinements[k]
        return RefineResult(method=method, object_name=name, model=self.model, foreground=fg, background=bg,
                            mask_values=torch.sigmoid(logits), ambiguous_final=s["ambiguous_final"],
                            num_gaussians_start=s["num_gaussians_start"], num_gaussians_end=len(self.model),
                            wall_s=s["wall_s"], peak_mem_bytes=self.peak_mem_bytes, config=s["config"])


def assign_object_ids(object_logits: Tensor) -> Tensor:
    """[N] int64 object id from [N, K] label logits: k + 1 for the object with the
    highest label among those with label > 0.9; 0 where none is above 0.9."""
    if object_logits.dim() != 2:
        raise InputError(f"object_logits must be [N, K], got {list(object_logits.shape)}")
    lg = object_logits.detach()
    best, arg = lg.max(dim=1)
    t_fg = math.log(FG_THRESHOLD / (1.0 - FG_THRESHOLD))
    return torch.where(best > t_fg, arg + 1, torch.zeros_like(arg)).to(torch.int64)


def refine_objects(
    model: GaussianModel,
    views: Sequence[View],
    masks: Mapping[str, Sequence[Optional[Tensor]]],
    extent: float,
    config: RefineConfig = RefineConfig(),
    *,
    background: Sequence[float] = (0.0, 0.0, 0.0),
    progress: "Progress" = True,
    texture_moments: Optional[Moments] = None,
) -> MultiObjectResult:
    """Refine and segment K objects in one run (see the module docstring).

    Each object's foreground here is its label column > 0.9 (the authors' segmentation):
    ``config.object_check`` (docs/method.md §7) is not applied to the joint result, whose
    object ids come from the labels alone; refine objects one at a time (:func:`refine`, as
    the refine stage does) for the checked foreground.

    Args:
        model: the trained scene (not modified; a clone is refined).
        views: training views.
        masks: object name → one mask per view, in refinement order.
        extent, config, background, progress: as in :func:`refine`.
        texture_moments: the baseline's Adam moments: the first object's texture stages
            start from them, every later object's from where the previous object's texture
            Adam ended (edited with its splits and prunes), as one continued optimisation.
    """
    names = list(masks)
    if not names:
        raise InputError("refine_objects needs at least one object")
    for n in names:
        if len(masks[n]) != len(views):
            raise InputError(f"object {n!r}: got {len(masks[n])} masks for {len(views)} views")
    m = model.clone()
    for extra in (OBJECT_LOGITS, OBJECT_ID):
        if extra in m.data:
            m.remove_extra(extra)
    t0 = time.perf_counter()
    summaries: list[dict] = []
    final: list[Optional[StageStats]] = []
    with PeakMemory() as mem:
        moments = texture_moments
        for name in names:
            r = refine(m, views, masks[name], extent, config, background=background, object_name=name,
                       progress=progress, copy=False, texture_moments=moments, return_moments=True)
            moments = r.texture_moments if r.config["texture_adam"] == "baseline" else None
            summaries.append(r.summary() | {"ambiguous_final": r.ambiguous_final})
        # Final label-only pass: one MASK stage per earlier object on the final scene.
        label_cfg = dataclasses.replace(config, bags=False, bgtr=False, raem="off", mask_stages=1,
                                        record_scores=False)
        last_labels = m.data[config.label_name].detach().clone()
        cols = []
        for k, name in enumerate(names):
            if k == len(names) - 1:
                cols.append(last_labels)
                final.append(None)
                continue
            pr = Refiner(m, views, masks[name], extent, label_cfg, background)
            stats, _, _ = pr.run(progress=progress, desc=f"labels {name}")
            st = stats[0]
            st.kind = "label_pass"
            final.append(st)
            cols.append(m.data[config.label_name].detach().clone())
        obj = torch.stack(cols, 1)
        # The working label extra ends as the last object's (as after its refinement).
        m.set_tensor(config.label_name, last_labels)
        m.add_extra(OBJECT_LOGITS, obj, fill=0.0)
        m.add_extra(OBJECT_ID, assign_object_ids(obj), fill=0)
    return MultiObjectResult(model=m, object_names=names, refinements=summaries, final_pass=final,
                             wall_s=time.perf_counter() - t0, peak_mem_bytes=mem.peak_bytes)
