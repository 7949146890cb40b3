"""Configs of COB-GS's refinement and of the peers (cobgs.refine)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import ClassVar, Optional

from cobgs.errors import InputError

from .checks import check_params
from .train import TrainConfig

LABEL = "mask_logit"  # name of the per-Gaussian label-logit extra
#: What the no-split peer forces on COB-GS's config (paper Table 5, first row; with the
#: stage count, cobgs.refine.peers.nosplit_config): these switches say nothing of a no-split row.
NOSPLIT_SWITCHES = {"bags": False, "bgtr": False, "raem": "off", "object_check": "off", "split_object_share": 0.0}
CHECKED = ("visible", "per_use")  # the object_check values that run the object-render check
RAEM_VARIANTS = ("off", "released", "paper")
SCENE_DEFAULTS = {"forward": (0.5, 6), "360": (0.8, 4)}  # δ, mask stages (docs/method.md §2)
TEXTURE_ADAM = ("baseline", "fresh")
FOREGROUND_LABEL = 0.9  # docs/method.md §2 segmentation: foreground = label > 0.9


# -- COB-GS refinement (cobgs.refine.alternation); the texture stage's lrs are the baseline's (docs/method.md §2)
@dataclass(frozen=True)
class RefineConfig:
    """Every parameter of the COB-GS refinement (defaults: the released behaviour, except
    RAEM: the paper's variant, which the benchmark's headline protocol supports — README,
    "Segmentation benchmark"; ``raem="released"`` is the authors' code).

    Attributes:
        scene_type: "forward" (δ 0.5, 6 mask + 5 texture stages) or "360" (δ 0.8, 4 + 3).
        delta: ambiguity threshold δ; None = the scene type's.
        mask_stages: number of MASK stages; None = the scene type's. TEXTURE stages sit
            between consecutive MASK stages (mask_stages − 1 of them) when ``bgtr``.
        stage_length_views: stage length in units of V (2 → 2V iterations).
        bags: boundary-adaptive Gaussian splitting on/off (Table 5).
        bgtr: boundary-guided texture restoration (TEXTURE stages) on/off (Table 5).
        raem: final pruning: "off", "released" (every ambiguous Gaussian) or "paper"
            (ambiguous and below the pixel footprint; :mod:`cobgs.refine.split`).
        score: "count" (pixel counts N⁺/N⁻, released) or "weight" (Σ α·T, ablation).
        texture_adam: "baseline" — the TEXTURE stages' Adam starts from the baseline's
            moments when the caller passes them (``texture_moments``; the released code
            restores the 3DGS checkpoint's optimizer), zero moments otherwise; "fresh" —
            always zero moments (ablation).
        split_size_fraction: split only ambiguous Gaussians with max scale > this × extent.
        split_children: children per split parent.
        split_scale_divisor: child scale = parent scale / this.
        raem_footprint_px: pixel-footprint threshold of the "paper" RAEM.
        mask_lambda: λ of the mask loss (weight of the background term).
        label_lr: Adam lr of the label logits.
        adam_eps: Adam epsilon of both optimizers.
        position_lr: texture-stage position lr (× extent): the baseline's final lr.
        sh0_lr, shN_lr, opacity_lr, scaling_lr, rotation_lr: texture-stage lrs (3DGS).
        ssim_weight: λ of the photometric loss 0.8·L1 + 0.2·(1 − SSIM).
        seed: seeds the view order and the split samples.
        backend: rasterizer backend.
        label_name: name of the label-logit extra.
        record_scores: keep every mask stage's mean scores in the result (δ sweep).
        object_check: "visible" (this project's addition, not the authors'): after the last
            stage, the foreground is rendered alone in every training view and a Gaussian
            whose votes there fall more on the mask's background than on its object (pixels
            where something else hides the object left out) leaves the foreground
            (:mod:`cobgs.refine.consistency`); "off": the released segmentation (label > 0.9);
            "per_use" (the default): two outputs of one refinement, each for its use
            (docs/method.md §7): the checked foreground for the object alone (extraction, the
            object-only protocols), the released one (label > 0.9) for the object rendered
            within the scene (``RefineResult.foreground_in_scene``, the occlusion-aware protocol).
    """

    scene_type: str = "forward"
    delta: Optional[float] = None
    mask_stages: Optional[int] = None
    stage_length_views: float = 2.0
    bags: bool = True
    bgtr: bool = True
    raem: str = "paper"
    score: str = "count"
    texture_adam: str = "baseline"
    split_size_fraction: float = 0.01
    split_children: int = 2
    split_scale_divisor: float = 1.6
    raem_footprint_px: float = 1.0
    mask_lambda: float = 1.0
    label_lr: float = 0.1
    adam_eps: float = 1e-15
    position_lr: float = TrainConfig.position_lr_final
    sh0_lr: float = TrainConfig.sh0_lr
    shN_lr: float = TrainConfig.shN_lr
    opacity_lr: float = TrainConfig.opacity_lr
    scaling_lr: float = TrainConfig.scaling_lr
    rotation_lr: float = TrainConfig.rotation_lr
    ssim_weight: float = TrainConfig.ssim_weight
    seed: int = 0
    backend: str = "native"
    label_name: str = LABEL
    record_scores: bool = True
    object_check: str = field(default="per_use", metadata={"before": "off"})  # entries before it: no check
    # The check's votes discounted where the masks are least reliable (issue 59 item 2): pixels
    # within this many pixels of a mask's edge are left out of the check, as hidden pixels are.
    # A Gaussian whose every pixel is near an edge (a thin or tiny object under noisy masks) then
    # keeps its label's verdict rather than being removed on the edge's say-so. 0: every pixel
    # votes (the check as measured in issue 48). Measured at 2 px on orbit_coarse (2026-11-29):
    # worse (the edge pixels remove the thin pole's spill); off.
    object_check_edge_px: int = field(default=0, metadata={"before": 0, "only_with": ("object_check", CHECKED)})
    # The check's keep rule (issue 59 item 2; cobgs.refine.consistency): "iou" (the default
    # since 2026-11-29), a Gaussian leaves only when the object's render agrees better with the
    # masks without it (soft IoU), so an object is never emptied of the few Gaussians that draw
    # it; "votes", the mask loss's rule per Gaussian (object votes > λ × background votes; the
    # check before, entries written then). Out of the key while the check is off.
    object_check_rule: str = field(default="iou", metadata={"before": "votes", "only_with": ("object_check", CHECKED)})
    # Ambiguity as the object sees it (issue 59 item 2; docs/method.md §7): at the end of each
    # mask stage a Gaussian whose minority Σ α·T (min of its object and background parts)
    # averages at least this share of the object's Σ α·T per view is split as an ambiguous one
    # is (when large), though Eq. 6 calls it unambiguous: a large Gaussian over a tiny or thin
    # object and much background. Never pruned by RAEM. 0: off (COB-GS as published; entries
    # written before the field existed).
    split_object_share: float = field(default=0.05, metadata={"before": 0.0})
    # RAEM never removes a Gaussian the labels call object (label > 0.9; issue 59 item 2): the
    # paper's RAEM takes tiny ambiguous Gaussians for residue of erroneous masks, but a thin
    # object is drawn by exactly such Gaussians (orbit_dense's pole: 308 of its 989, 4 points of
    # mBIoU); with this on, the object-render check, which weighs the masks' evidence, judges
    # them instead. Off: RAEM as published (entries written before). Measured on the nine rows
    # with tests/benchmarks/bm_raem.py (docs/benchmarks/segmentation.md): it gives the pole back
    # (+4.3) but RAEM's pruning also cleans larger objects' silhouettes, and without it the
    # headline falls significantly on three rows (−0.02 … −0.23); rejected as a default.
    raem_spare_object: bool = field(default=False, metadata={"before": False,
                                                              "only_with": ("raem", ("released", "paper"))})
    # RAEM's object Gaussians judged per object by the training masks (issue 59 item 2): where RAEM
    # would prune Gaussians the labels call object, both outcomes (pruned as published, or spared
    # as raem_spare_object spares them) go through the final sets (the check), and the one whose
    # object alone, drawn above 0.5, agrees better with the training masks wins (IoU over the
    # judged pixels, the pixels where something else hides the object left out; a tie: as
    # published). Measured on the nine rows as bm_raem's "object_set" (segmentation.md); off.
    raem_object_by_masks: bool = field(default=False, metadata={"before": False,
                                                                 "only_with": ("raem", ("released", "paper"))})
    # The object within the scene (the ``per_use`` check's second output, the occlusion-aware
    # protocol; issue 59 item 2): "votes" (the default since 2026-11-29), the labels' verdict
    # plus every Gaussian the refinement left undecided (0.1 < label < 0.9: split late, or
    # judged on little evidence) whose Σ α·T votes of the training masks in the scene render say
    # object (object votes > λ × background votes: the mask loss's own closed form;
    # cobgs.refine.consistency.undecided_by_votes); "labels", the labels' verdict alone (label >
    # 0.9, as released; entries written before). Measured on eight baselines of the two coarse
    # scenes: +0.07 … +0.99 occlusion-aware mBIoU pooled, never significantly below (docs/
    # benchmarks/segmentation.md). Out of the key unless the check is per_use.
    in_scene_undecided: str = field(default="votes", metadata={"before": "labels",
                                                                 "only_with": ("object_check", ("per_use",))})

    RANGES: ClassVar[dict] = {
        "delta": "[0, 1]", "mask_stages": "[1, 100]", "stage_length_views": "(0, 100]",
        "split_size_fraction": "[0, 1]", "split_children": "[1, 16]", "split_scale_divisor": "[1, 100]",
        "raem_footprint_px": "[0, 1e4]", "mask_lambda": "[0, 1000]", "label_lr": "(0, 10]",
        "adam_eps": "(0, 0.001]", "position_lr": "[0, 1]", "sh0_lr": "[0, 1]", "shN_lr": "[0, 1]",
        "opacity_lr": "[0, 1]", "scaling_lr": "[0, 1]", "rotation_lr": "[0, 1]", "ssim_weight": "[0, 1]",
        "seed": "[0, 2147483647]", "object_check_edge_px": "[0, 64]", "split_object_share": "[0, 1]",
    }
    CHOICES: ClassVar[dict] = {"backend": ("native", "reference"), "label_name": (LABEL,),
                               "scene_type": tuple(SCENE_DEFAULTS), "raem": RAEM_VARIANTS,
                               "score": ("count", "weight"), "texture_adam": TEXTURE_ADAM,
                               "object_check": ("off", *CHECKED),
                               "object_check_rule": ("votes", "iou", "removal"),
                               "in_scene_undecided": ("labels", "votes")}

    def __post_init__(self):
        check_params(self)  # (every field's range and choices: RANGES / CHOICES above)
        if self.raem_object_by_masks and self.raem_spare_object:
            raise InputError("RefineConfig: raem_object_by_masks and raem_spare_object are both on; "
                             "expected at most one (raem_object_by_masks already weighs the spared set)")

    @property
    def threshold(self) -> float:
        """δ actually used."""
        return SCENE_DEFAULTS[self.scene_type][0] if self.delta is None else float(self.delta)

    @property
    def num_mask_stages(self) -> int:
        return SCENE_DEFAULTS[self.scene_type][1] if self.mask_stages is None else self.mask_stages

    def stage_length(self, num_views: int) -> int:
        """Iterations per stage: round(stage_length_views × V), at least 1."""
        return max(1, int(round(self.stage_length_views * num_views)))

    def steps_to_foreground(self) -> int:
        """Fewest MASK iterations that can carry a label from 0.5 (logit 0, where labels start
        and split children restart) past the 0.9 foreground threshold: Adam moves a logit by
        at most about ``label_lr`` per step, so ⌈ln 9 / lr⌉ (22 at the default lr 0.1;
        docs/method.md §2, "Few views")."""
        return int(math.ceil(math.log(FOREGROUND_LABEL / (1.0 - FOREGROUND_LABEL)) / self.label_lr - 1e-9))

    def stages_too_short(self, num_views: int) -> bool:
        """Whether splitting is on and stages of ``num_views`` views are shorter than
        :meth:`steps_to_foreground` (without splits, labels keep training across stages)."""
        return self.bags and self.stage_length(num_views) < self.steps_to_foreground()

    def min_stage_length_views(self, num_views: int) -> float:
        """The smallest ``stage_length_views`` in steps of 0.1 with ``stage_length_views × V``
        (V = ``num_views``) at least :meth:`steps_to_foreground`, before any rounding."""
        return math.ceil(self.steps_to_foreground() / max(num_views, 1) * 10 - 1e-9) / 10

    def plan(self) -> list[str]:
        """Stage kinds in order: "mask" / "texture", starting and ending with "mask"."""
        out = []
        for i in range(self.num_mask_stages):
            out.append("mask")
            if self.bgtr and i < self.num_mask_stages - 1:
                out.append("texture")
        return out

    def as_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["threshold"] = self.threshold
        d["num_mask_stages"] = self.num_mask_stages
        return d


# -- peers (cobgs.refine.peers) ------------------------------------------------------------------
@dataclass(frozen=True)
class SA3DConfig:
    """SA3D-GS parameters (docs/method.md §3, "SA3D-GS"). The defaults are the
    official ``sa3d-gs`` rules (``train_seg.py``, ``gaussian_model.py``, ``render.py``);
    :meth:`strict` is the stricter variant this project ran before (a stronger peer, kept
    as an option and a benchmark row) and :meth:`binary` the official training rendered
    with mask value 1 and thresholded at 0.5 (a named row that separates the training from
    the evaluation's 0.1 bar on raw labels).

    Attributes:
        lr: Adam lr of the raw labels.
        neg_weight: weight of the background term of the loss.
        passes: passes over the training views.
        order: "fixed" (the views in their given order each pass, official) or "random"
            (shuffled per pass with ``seed``).
        skip_iou: in the **first** pass a view whose mask rendered from the current labels
            (> ``gate_threshold``) has IoU below this with the view's mask is skipped and
            remembered (official: 0.5; the first view of the pass is never tested);
            later passes test nothing and skip exactly the remembered views
            (``train_seg.py:229-250``); 0 = never skip.
        gate_threshold: the rendered mask is binarised above this for the gate (official
            0.5, ``train_seg.py:229-231``; not the evaluation's ``render_threshold``).
        label_threshold: foreground = raw label > this at the end (official: 0); the same
            test removes the Gaussians with label <= 0 between passes 1 and 2.
        keep_all_if_none: when no Gaussian passes ``label_threshold`` (after pass 1, and
            at the end), keep every Gaussian instead of none (official
            ``GaussianModel.segment``: "the mask is empty, segmenting the whole point
            cloud").
        render_values: what the object render composites per foreground Gaussian:
            "label" (its raw label, official) or "one".
        render_threshold: the object render is foreground above this (official: 0.1).
        seed: view order when ``order`` is "random".
        adam_eps: Adam epsilon.
        backend: rasterizer backend.
    """

    lr: float = 1.0
    neg_weight: float = 0.3
    passes: int = 2
    order: str = "fixed"
    skip_iou: float = 0.5
    gate_threshold: float = 0.5
    label_threshold: float = 0.0
    keep_all_if_none: bool = True
    render_values: str = "label"
    render_threshold: float = 0.1
    seed: int = 0
    adam_eps: float = 1e-15
    backend: str = "native"

    # gate / label / render_threshold compare raw (unbounded) labels or their composited
    # render: no range but finiteness (check_params' rule for a float without one)
    RANGES: ClassVar[dict] = {"lr": "(0, 100]", "neg_weight": "[0, 100]", "passes": "[1, 100]",
                              "skip_iou": "[0, 1]", "adam_eps": "(0, 0.001]", "seed": "[0, 2147483647]"}
    CHOICES: ClassVar[dict] = {"backend": ("native", "reference"), "order": ("fixed", "random"),
                               "render_values": ("label", "one")}

    def __post_init__(self):
        check_params(self)

    @classmethod
    def strict(cls, **kw) -> "SA3DConfig":
        """The stricter variant: random order, no skipped views, label > 0.5 (no keep-all
        fallback) and the object's render (mask value 1 per foreground Gaussian)
        thresholded at 0.5."""
        return cls(**{"order": "random", "skip_iou": 0.0, "label_threshold": 0.5, "keep_all_if_none": False,
                      "render_values": "one", "render_threshold": 0.5, **kw})

    @classmethod
    def binary(cls, **kw) -> "SA3DConfig":
        """The official training, its segmentation (label > 0) rendered with mask value 1
        and thresholded at 0.5 instead of compositing the raw labels at 0.1."""
        return cls(**{"render_values": "one", "render_threshold": 0.5, **kw})


@dataclass(frozen=True)
class FlashSplatConfig:
    """FlashSplat parameters (docs/method.md §3).

    Attributes:
        background_bias: added to the normalised background entry before the argmax
            (upstream tunes it per scene in about [−0.98, 0.88]).
        backend: rasterizer backend.
    """

    background_bias: float = 0.0
    backend: str = "native"

    RANGES: ClassVar[dict] = {"background_bias": "[-2, 2]"}
    CHOICES: ClassVar[dict] = {"backend": ("native", "reference")}

    def __post_init__(self):
        check_params(self)


@dataclass(frozen=True)
class LUDVIGConfig:
    """LUDVIG (Marrie et al., ICCV 2025; released code naver/ludvig; docs/method.md §3): 2D masks
    uplifted to the Gaussians by weighted back-projection, no optimisation. Defaults: the
    release's ``configs/sam_NVOS.yaml`` and ``utils/solver.py``.

    Attributes:
        threshold_k: the evaluation keeps the pixels of the min-max normalised feature render
            above ``1 - k / 100`` (``thresholding: 75``; the release's SAM setting).
        thresholding: "fixed" (``threshold_k``) or "li" (Li's threshold of each normalised
            render, the release's setting for SAM2 masks).
        prune_quantile: the Gaussians whose summed rendering weight is at or below this quantile
            leave the scene (``prune_gaussians: .50``) ...
        prune_min_gaussians: ... only when the scene holds more than this many
            (``uplifting(min_gaussians=400000)``).
        backend: rasterizer backend.
    """

    threshold_k: float = 75.0
    thresholding: str = "fixed"
    prune_quantile: float = 0.5
    prune_min_gaussians: int = 400_000
    backend: str = "native"

    RANGES: ClassVar[dict] = {"threshold_k": "(0, 100)", "prune_quantile": "[0, 1)",
                              "prune_min_gaussians": "[0, 1e9]"}
    CHOICES: ClassVar[dict] = {"backend": ("native", "reference"), "thresholding": ("fixed", "li")}

    def __post_init__(self):
        check_params(self)


@dataclass(frozen=True)
class NGSConfig:
    """NG-GS's boundary stage (cobgs.refine.ngs; docs/method.md §3 "NG-GS"). Defaults: the
    released ``arguments/__init__.py`` and ``scene/ngs_model.py``.

    Attributes:
        lr: the refiner's Adam learning rate (``ngs_lr``).
        max_points: boundary Gaussians per texture iteration (``ngs_max_points``).
        lambda_align, lambda_cont, lambda_smooth: the loss weights (``lambda_ngs_*``).
        hash_levels, features_per_level, log2_hashmap_size, base_resolution,
        finest_resolution: the hash encoding; hidden_dim: the MLP width; k_neighbors: the
        RBF neighbourhood.
        seed: the refiner's initialisation, the jitter and the random subset.
    """

    lr: float = 1e-3
    max_points: int = 4096
    lambda_align: float = 1.0
    lambda_cont: float = 0.1
    lambda_smooth: float = 0.05
    hash_levels: int = 8
    features_per_level: int = 2
    log2_hashmap_size: int = 15
    base_resolution: int = 16
    finest_resolution: int = 512
    hidden_dim: int = 64
    k_neighbors: int = 8
    seed: int = 0

    RANGES: ClassVar[dict] = {"lr": "(0, 1]", "max_points": "[1, 1e8]", "lambda_align": "[0, 1e3]",
                              "lambda_cont": "[0, 1e3]", "lambda_smooth": "[0, 1e3]", "hash_levels": "[1, 32]",
                              "features_per_level": "[1, 64]", "log2_hashmap_size": "[4, 28]",
                              "base_resolution": "[1, 1e6]", "finest_resolution": "[1, 1e6]",
                              "hidden_dim": "[1, 4096]", "k_neighbors": "[1, 1024]", "seed": "[0, 2147483647]"}

    def __post_init__(self):
        check_params(self)
        if self.finest_resolution < self.base_resolution:
            raise InputError(f"NGSConfig.finest_resolution ({self.finest_resolution}) must be >= base_resolution "
                             f"({self.base_resolution})")


