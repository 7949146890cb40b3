"""Every configuration of the library, in one module that imports nothing heavy.

The dataclasses and their validation only, each with this one import path: the algorithm
modules and the pipeline's stages import them from here (the stages declare them as their
params directly), so ``cobgs --help`` and a fully cached ``cobgs run`` never import
torch (or numpy) to read a workflow, and every value is checked where it is set.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
from dataclasses import dataclass, field
from typing import ClassVar, Optional, Tuple

from cobgs.errors import InputError

__all__ = ["Files", "DatasetConfig", "NGSConfig", "NOSPLIT_SWITCHES", "key_without_later", "with_later_values", "check_params", "parse_interval", "in_interval", "TrainConfig", "Schedule", "RefineConfig",
           "SA3DConfig", "FlashSplatConfig", "TwoStageConfig", "ScribbleConfig", "MaskNoiseParams", "SfmOptions", "LABEL",
           "RAEM_VARIANTS", "TEXTURE_ADAM", "SCENE_DEFAULTS", "MATCHERS"]

LABEL = "mask_logit"  # name of the per-Gaussian label-logit extra
#: What the no-split peer forces on COB-GS's config (paper Table 5, first row; with the
#: stage count, cobgs.refine.peers.nosplit_config): these switches say nothing of a no-split row.
NOSPLIT_SWITCHES = {"bags": False, "bgtr": False, "raem": "off", "object_check": "off"}
RAEM_VARIANTS = ("off", "released", "paper")
SCENE_DEFAULTS = {"forward": (0.5, 6), "360": (0.8, 4)}  # δ, mask stages (docs/method.md §2)
TEXTURE_ADAM = ("baseline", "fresh")
MATCHERS = ("auto", "exhaustive", "sequential")


# -- the artifact catalog ------------------------------------------------------------------
class Files:
    """The file names inside each stage's artifact, named once: the stages write them, and
    the library, ``cobgs export`` and the report read them from here (kedro's catalog idea:
    each artifact named in one place)."""

    DATASET = "dataset.json"  # dataset: the scene's typed record (cobgs.data.spec)
    SFM = "sfm.json"  # sfm: what SfM or triangulation did
    SFM_IMAGES = "images"  # sfm: the (undistorted) images
    SFM_MODEL = "sparse/0"  # sfm: the COLMAP model
    SFM_POINTS = "points.npz"  # sfm: points triangulated with known poses
    TRAIN = "train.json"  # train: config, schedule, views, held-out metrics, history
    SCENE_PLY = "scene.ply"  # train: the trained scene (standard 3DGS layout)
    MOMENTS = "adam_moments.pt"  # train: the Adam state (cobgs.train.adam_moments)
    RENDERS = "renders"  # train: held-out renders, <view>.png
    MASKS = "masks.json"  # masks: how the masks were made (<view>.png beside it)
    HELDOUT = "heldout.json"  # heldout: the ground-truth pictures written
    REFINE = "refine.json"  # refine: what the method did
    REFINED_PLY = "refined.ply"  # refine: the scene after the method, labels as extras
    SEGMENTATION = "segmentation.npz"  # refine: labels / foreground per Gaussian
    STAGE_SCORES = "stage_scores.npz"  # refine: per-stage scores
    RAEM_REMOVED = "raem_removed.ply"  # refine: what RAEM removed (restored for the scene render)
    SEGMENT = "segment.json"  # segment: counts, timings, views
    OBJECT_PLY = "object.ply"  # segment: the object alone
    BACKGROUND_PLY = "background.ply"  # segment: the scene without it
    PRED_MASKS = "pred_masks"  # segment: predicted masks, <view>.png
    METRICS = "metrics.json"  # evaluate: the row and its details
    PER_VIEW = "per_view.csv"  # evaluate: one line per view
    SUMMARY = "summary.json"  # summary: every table
    SUMMARY_CSV = "summary.csv"  # summary: the rows
    BY_METHOD = "by_method.csv"
    BY_SCENE_METHOD = "by_scene_method.csv"
    TIMINGS = "timings.csv"
    SCENES = "scenes.csv"
    EXPORT_MARKER = "export.json"  # cobgs export: what was copied (pipeline.publish's marker)
    REPORT_MARKER = "report.json"  # cobgs report: the report's record (the same)


# -- valid ranges ------------------------------------------------------------------------
# Every config (and the pipeline's stage params) states the valid range of its numeric
# fields once, as a class attribute RANGES = {field: "[lo, hi]"} ("(" / ")" for an open
# end, inf allowed), and the allowed values of its string fields as CHOICES; check_params
# enforces both in __post_init__, and the docs' table of params is generated from them
# (docs/pipeline.md, `cobgs stages --toml`). A float field without a range must be finite.
_INTERVAL = re.compile(r"^\s*([\[(])\s*([^,\s]+)\s*,\s*([^\])\s]+)\s*([\])])\s*$")


def parse_interval(text: str) -> tuple[float, float, bool, bool]:
    """(lo, hi, lo_closed, hi_closed) of an interval written "[0, 1)", "(0, inf]" ..."""
    m = _INTERVAL.match(text)
    if m is None:
        raise ValueError(f"bad interval {text!r} (expected e.g. '[0, 1]' or '(0, inf)')")
    return float(m.group(2)), float(m.group(3)), m.group(1) == "[", m.group(4) == "]"


def in_interval(x: float, text: str) -> bool:
    lo, hi, lo_c, hi_c = parse_interval(text)
    if x != x:  # nan
        return False
    return (x >= lo if lo_c else x > lo) and (x <= hi if hi_c else x < hi)


def check_params(obj) -> None:
    """Enforce ``type(obj).RANGES`` / ``CHOICES`` (see above) on a dataclass instance.

    Raises:
        InputError: naming the class, the field, the valid range or values, and the value.
    """
    cls = type(obj)
    ranges = getattr(cls, "RANGES", {})
    choices = getattr(cls, "CHOICES", {})
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        allowed = choices.get(f.name)
        if allowed is not None and v is not None and v not in allowed:
            raise InputError(f"{cls.__name__}.{f.name} must be one of {list(allowed)}, got {v!r}")
        spec = ranges.get(f.name)
        for x in (v if isinstance(v, (tuple, list)) else (v,)):
            if isinstance(x, bool) or not isinstance(x, (int, float)):
                continue
            try:
                fx = float(x)
            except OverflowError:  # an int past any float: outside every range
                fx = math.inf if x > 0 else -math.inf
            if spec is not None:
                if not in_interval(fx, spec):
                    raise InputError(f"{cls.__name__}.{f.name} must be in {spec}, got {_short(x)}")
            elif not math.isfinite(fx):
                raise InputError(f"{cls.__name__}.{f.name} must be a finite number, got {_short(x)}")


def _short(x) -> str:
    """A value for a message: a huge integer by its digit count, not its digits."""
    if isinstance(x, int) and abs(x) >= 10 ** 60:
        return f"an integer of {len(str(abs(x)))} digits"
    return repr(x)


# -- scenes (cobgs.data.build) ----------------------------------------------------------------------
@dataclass(frozen=True)
class DatasetConfig:
    """How a scene is generated or ingested (the dataset stage's params; cobgs.data.build).

    Attributes:
        preset: synthetic preset ("demo", "forward", "orbit").
        seed: synthetic seed.
        width_px, height_px, num_views, supersampling: synthetic overrides (0 = preset's).
        workers: processes rendering synthetic views (the output does not depend on it).
        downscale: divide the image size for training (LLFF: picks ``images_<k>/``).
        images_dir: image sub-folder SfM runs on ("" = ``images_<downscale>/`` when it
            exists, else ``images/``); when given, ``downscale`` applies after SfM.
        view_stride: keep every k-th view (sorted by name) — subsets of long captures.
        max_views: keep at most this many views after the stride (0 = all).
        test_every: hold out every k-th kept view when the data defines no split.
        background: RGB in [0, 1] that RGBA images are composited on (None: the reader's).
    """

    preset: str = "demo"
    seed: int = 0
    width_px: int = 0
    height_px: int = 0
    num_views: int = 0
    supersampling: int = 0
    workers: int = 1
    downscale: float = 1.0
    images_dir: str = ""
    view_stride: int = 1
    max_views: int = 0
    test_every: int = 8
    background: Optional[tuple[float, float, float]] = None

    RANGES: ClassVar[dict] = {
        "seed": "[0, 2147483647]", "width_px": "[0, 16384]", "height_px": "[0, 16384]", "num_views": "[0, 10000]",
        "supersampling": "[0, 16]", "workers": "[0, 256]", "downscale": "(0, 64]", "view_stride": "[1, 1e6]",
        "max_views": "[0, 1e6]", "test_every": "[0, 1e6]", "background": "[0, 1]"}

    def __post_init__(self) -> None:
        check_params(self)
        if self.view_stride < 1 or self.max_views < 0 or self.test_every < 0:
            raise ValueError("view_stride must be >= 1, max_views and test_every >= 0")
        if self.test_every == 1:
            raise ValueError("test_every = 1 holds out every view, leaving nothing to train on: 0 holds out "
                             "none, k >= 2 every k-th view")
        if not self.downscale > 0:
            raise ValueError(f"downscale must be > 0, got {self.downscale}")


# -- baseline training (cobgs.train.optimize) ---------------------------------------------------------
RECIPES_NAMES = ("3dgs", "fast")  # (the recipes' values: RECIPES, below the class)
@dataclass(frozen=True)
class TrainConfig:
    """Every knob of the baseline optimisation (defaults: the 3DGS paper's)."""

    iterations: Optional[int] = field(default=None, metadata={"help": (
        "unset: the recipe's (3dgs: the paper's 30 000; fast: 12 000); the shipped workflows "
        "and `cobgs new` set 7000, the 3DGS short schedule (compressed by scale_schedule)")})
    seed: int = 0
    # Schedule scaling (see the module docstring).
    scale_schedule: bool = True
    scale_densify_interval: bool = False
    reference_iterations: int = 30_000
    # Spherical harmonics.
    sh_degree: int = 3
    sh_degree_interval_its: int = 1_000
    # Learning rates (Adam, eps 1e-15). Position lr is multiplied by the scene extent.
    position_lr_init: float = 1.6e-4
    position_lr_final: float = 1.6e-6
    position_lr_decay_its: int = 30_000
    sh0_lr: float = 2.5e-3
    shN_lr: float = 2.5e-3 / 20.0
    opacity_lr: float = 0.025
    scaling_lr: float = 5e-3
    rotation_lr: float = 1e-3
    adam_eps: float = 1e-15
    ssim_weight: float = 0.2
    # Densification.
    densify_from_its: int = 500
    densify_until_its: int = 15_000
    densify_interval_its: int = 100
    densify_grad_threshold_ndc: float = 2e-4
    dense_scale_fraction: float = 0.01  # clone if max scale <= this x extent, else split
    split_children: int = 2
    split_scale_divisor: float = 1.6
    prune_min_opacity: float = 0.005
    prune_max_world_scale_fraction: float = 0.1  # x extent, after the first opacity reset
    prune_max_screen_radius_px: float = 0.0  # 0 = off (see the module docstring)
    max_gaussians: int = 0  # 0 = unlimited; otherwise densification stops adding
    opacity_reset_interval_its: int = 3_000
    opacity_reset_value: float = 0.01
    # Initialisation.
    random_init_points: int = 100_000
    init_opacity: float = 0.1
    # Rendering / bookkeeping.
    background: Optional[tuple[float, float, float]] = None  # None: the scene's
    # A fresh uniform-random background colour every iteration (3DGS's ``--random_background``):
    # a fully opaque capture can then no longer be fitted by letting a fixed black
    # background show through semi-transparent layers; only for opaque photographs
    # (not RGBA-composited scenes, whose targets contain the fixed background).
    random_background: bool = False
    backend: str = "native"
    log_interval_its: int = 10
    checkpoint_interval_its: int = 0  # 0 = only at the end (when a folder is given)
    # -- the recipe and the switches of the fast one (docs/method.md §1, "Recipes") --------------
    # Fields added after the first cache entries were written carry metadata "before": the
    # value every run had before the field existed; the train stage's key leaves a field out
    # while it holds that value (cobgs.configs.key_without_later), so earlier entries stay valid.
    recipe: str = field(default="3dgs", metadata={"before": "3dgs", "help": (
        '"3dgs": the paper\'s schedule as written; "fast": RECIPES["fast"] for the fields left '
        "unset (iterations, resolution_schedule, the budget's fields)")})
    # DashGaussian-style resolution schedule: render at 1/d of the image size, d chosen so that
    # the share of the images' spectral energy below the rendered Nyquist grows linearly from
    # what 1/resolution_max_downscale holds to all of it at resolution_full_at x iterations.
    resolution_schedule: Optional[bool] = field(default=None, metadata={"before": False, "help": (
        "unset: the recipe's (3dgs: false, fast: true)")})
    resolution_max_downscale: float = field(default=4.0, metadata={"before": 4.0})
    resolution_full_at: float = field(default=0.5, metadata={"before": 0.5})
    # Taming-3DGS-style budget: densification follows a count that grows linearly from the
    # initial points to the budget at budget_full_at of the densification window, densifying
    # the Gaussians of highest score (the averaged view-space gradient) first; the budget is
    # never exceeded. Absolute (wins where set), else the larger of a per-pixel budget (of one
    # training image) and a multiple of the initial count (Taming's "multiplier" mode: the SfM
    # points, or the random box's random_init_points). 0 everywhere: no budget.
    gaussian_budget: int = field(default=0, metadata={"before": 0})
    gaussian_budget_per_pixel: Optional[float] = field(default=None, metadata={"before": 0.0, "help": (
        "unset: the recipe's (3dgs: 0 = no budget, fast: 0.3)")})
    gaussian_budget_multiplier: Optional[float] = field(default=None, metadata={"before": 0.0, "help": (
        "unset: the recipe's (3dgs: 0, fast: 36)")})
    budget_full_at: float = field(default=0.7, metadata={"before": 0.7})
    # The budget as a ceiling rather than a target: only Gaussians over 3DGS's gradient threshold
    # are candidates (highest first, as many as the line allows), so a budget the scene does not
    # need leaves 3DGS's own densification as it is. Off: Taming's rule (the line is reached).
    budget_threshold_gate: Optional[bool] = field(default=None, metadata={"before": False, "help": (
        "unset: the recipe's (3dgs: false, fast: true)")})
    # Adam steps only the Gaussians the view touches (radius > 0): the others keep their
    # parameters and moments, as gsplat's selective Adam.
    sparse_adam: bool = field(default=False, metadata={"before": False})
    # The CPU blending kernels' fast path in the training steps (fused multiply-adds; images and
    # gradients within tests/render/test_cpu_fast_path.py's tolerances of the exact kernels,
    # no longer bit-identical to them or to CUDA). Evaluation, refinement and export keep the
    # exact kernels. CUDA has its own switch (COBGS_CUDA_EXACT).
    fast_kernels: bool = field(default=False, metadata={"before": False})

    RANGES: ClassVar[dict] = {
        "iterations": "[1, 1e7]", "seed": "[0, 2147483647]", "reference_iterations": "[1, 1e7]",
        "sh_degree": "[0, 3]", "sh_degree_interval_its": "[1, 1e7]",
        "position_lr_init": "(0, 1]", "position_lr_final": "(0, 1]", "position_lr_decay_its": "[1, 1e7]",
        "sh0_lr": "[0, 1]", "shN_lr": "[0, 1]", "opacity_lr": "[0, 1]", "scaling_lr": "[0, 1]",
        "rotation_lr": "[0, 1]", "adam_eps": "(0, 0.001]", "ssim_weight": "[0, 1]",
        "densify_from_its": "[0, 1e7]", "densify_until_its": "[0, 1e7]", "densify_interval_its": "[1, 1e7]",
        "densify_grad_threshold_ndc": "(0, 1]", "dense_scale_fraction": "[0, 1]", "split_children": "[1, 16]",
        "split_scale_divisor": "[1, 100]", "prune_min_opacity": "[0, 1)",
        "prune_max_world_scale_fraction": "(0, inf]", "prune_max_screen_radius_px": "[0, inf]",
        "max_gaussians": "[0, 1e9]", "opacity_reset_interval_its": "[1, 1e7]", "opacity_reset_value": "(0, 1)",
        "random_init_points": "[1, 1e8]", "init_opacity": "(0, 1)", "background": "[0, 1]",
        "log_interval_its": "[1, 1e7]", "checkpoint_interval_its": "[0, 1e7]",
        "resolution_max_downscale": "[1, 64]", "resolution_full_at": "(0, 1]", "gaussian_budget": "[0, 1e9]",
        "gaussian_budget_per_pixel": "[0, 100]", "gaussian_budget_multiplier": "[0, 10000]",
        "budget_full_at": "(0, 1]",
    }
    CHOICES: ClassVar[dict] = {"backend": ("native", "reference"), "recipe": tuple(RECIPES_NAMES)}

    def __post_init__(self):
        check_params(self)
        for name, value in RECIPES[self.recipe].items():  # what the caller left unset: the recipe's
            if getattr(self, name) is None:
                object.__setattr__(self, name, value)

    def budget_for(self, width: int, height: int, initial: int = 0) -> int:
        """The Gaussian budget for training images of ``width`` x ``height`` and a model that
        starts with ``initial`` Gaussians, 0 for none: ``gaussian_budget`` where set, else the
        larger of ``gaussian_budget_per_pixel`` x the pixels and ``gaussian_budget_multiplier``
        x the initial count."""
        if self.gaussian_budget:
            return int(self.gaussian_budget)
        per_pixel = int(round(self.gaussian_budget_per_pixel * width * height))
        per_point = int(round(self.gaussian_budget_multiplier * max(0, int(initial))))
        return max(per_pixel, per_point)

    def schedule(self) -> "Schedule":
        """Iteration-valued fields after scaling to ``iterations`` (see module docstring)."""
        f = self.iterations / self.reference_iterations if self.scale_schedule else 1.0

        def s(v: int) -> int:
            return max(1, int(round(v * f)))

        return Schedule(
            sh_degree_interval=s(self.sh_degree_interval_its),
            position_lr_decay=s(self.position_lr_decay_its),
            densify_from=s(self.densify_from_its),
            densify_until=s(self.densify_until_its),
            densify_interval=s(self.densify_interval_its) if self.scale_densify_interval else self.densify_interval_its,
            opacity_reset_interval=s(self.opacity_reset_interval_its),
        )


#: The values a recipe gives the :class:`TrainConfig` fields the caller leaves unset (None)
#: (docs/method.md §1, "Recipes"; measured in docs/benchmarks/cost_cpu.md). A value the caller
#: sets, whatever it is, stays.
RECIPES = {
    "3dgs": {"iterations": 30_000, "resolution_schedule": False, "gaussian_budget_per_pixel": 0.0,
             "gaussian_budget_multiplier": 0.0, "budget_threshold_gate": False},
    "fast": {"iterations": 12_000, "resolution_schedule": True, "gaussian_budget_per_pixel": 0.3,
             "gaussian_budget_multiplier": 36.0, "budget_threshold_gate": True},
}
FAST_RECIPE = RECIPES["fast"]


def with_later_values(cls, params: dict) -> dict:
    """``params`` (a params object as JSON, as a manifest recorded it) with each field of
    ``cls`` added later and absent there filled in with the value runs had before it existed
    (field metadata "before"): an entry written before a switch reads as what it ran."""
    out = dict(params)
    for f in dataclasses.fields(cls):
        if "before" in f.metadata and f.name not in out:
            before = f.metadata["before"]
            out[f.name] = list(before) if isinstance(before, tuple) else before
    return out


def key_without_later(cls, full: dict) -> dict:
    """``full`` (a params object as JSON) without the fields of ``cls`` that were added
    later and hold the value every run had before they existed (field metadata "before"):
    a cache key made this way is the key the same run had before the field was added."""
    out = dict(full)
    for f in dataclasses.fields(cls):
        if "before" in f.metadata and f.name in out:
            before = f.metadata["before"]
            if out[f.name] == (list(before) if isinstance(before, tuple) else before):
                del out[f.name]
    return out


@dataclass(frozen=True)
class Schedule:
    """Resolved iteration counts of one run (see :meth:`TrainConfig.schedule`)."""

    sh_degree_interval: int
    position_lr_decay: int
    densify_from: int
    densify_until: int
    densify_interval: int
    opacity_reset_interval: int


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

    RANGES: ClassVar[dict] = {
        "delta": "[0, 1]", "mask_stages": "[1, 100]", "stage_length_views": "(0, 100]",
        "split_size_fraction": "[0, 1]", "split_children": "[1, 16]", "split_scale_divisor": "[1, 100]",
        "raem_footprint_px": "[0, 1e4]", "mask_lambda": "[0, 1000]", "label_lr": "(0, 10]",
        "adam_eps": "(0, 0.001]", "position_lr": "[0, 1]", "sh0_lr": "[0, 1]", "shN_lr": "[0, 1]",
        "opacity_lr": "[0, 1]", "scaling_lr": "[0, 1]", "rotation_lr": "[0, 1]", "ssim_weight": "[0, 1]",
        "seed": "[0, 2147483647]",
    }
    CHOICES: ClassVar[dict] = {"backend": ("native", "reference"), "label_name": (LABEL,),
                               "scene_type": tuple(SCENE_DEFAULTS), "raem": RAEM_VARIANTS,
                               "score": ("count", "weight"), "texture_adam": TEXTURE_ADAM,
                               "object_check": ("off", "visible", "per_use")}

    def __post_init__(self):
        check_params(self)
        if self.scene_type not in SCENE_DEFAULTS:
            raise InputError(f"RefineConfig.scene_type must be 'forward' or '360', got {self.scene_type!r}")
        if self.raem not in RAEM_VARIANTS:
            raise InputError(f"RefineConfig.raem must be one of {RAEM_VARIANTS}, got {self.raem!r}")
        if self.score not in ("count", "weight"):
            raise InputError(f"RefineConfig.score must be 'count' or 'weight', got {self.score!r}")
        if self.texture_adam not in TEXTURE_ADAM:
            raise InputError(f"RefineConfig.texture_adam must be one of {TEXTURE_ADAM}, got {self.texture_adam!r}")
        if self.delta is not None and not (0.0 <= self.delta <= 1.0):
            raise InputError(f"RefineConfig.delta must be in [0, 1], got {self.delta}")
        if self.mask_stages is not None and (not isinstance(self.mask_stages, int) or self.mask_stages < 1):
            raise InputError(f"RefineConfig.mask_stages must be an int >= 1, got {self.mask_stages!r}")
        if not self.stage_length_views > 0:
            raise InputError(f"RefineConfig.stage_length_views must be > 0, got {self.stage_length_views}")
        if self.split_children < 1 or self.split_scale_divisor <= 0:
            raise InputError("RefineConfig.split_children must be >= 1 and split_scale_divisor > 0")
        if self.mask_lambda < 0:
            raise InputError(f"RefineConfig.mask_lambda must be >= 0, got {self.mask_lambda}")
        for name in ("label_lr", "adam_eps"):
            if not getattr(self, name) > 0:
                raise InputError(f"RefineConfig.{name} must be > 0")

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
        if self.passes < 1 or not self.lr > 0:
            raise InputError("SA3DConfig.passes must be >= 1 and lr > 0")
        if self.order not in ("fixed", "random"):
            raise InputError(f"SA3DConfig.order must be 'fixed' or 'random', got {self.order!r}")
        if self.render_values not in ("label", "one"):
            raise InputError(f"SA3DConfig.render_values must be 'label' or 'one', got {self.render_values!r}")

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


# -- two-stage masks and scribbles (cobgs.masks) ------------------------------------------
@dataclass(frozen=True)
class TwoStageConfig:
    """Thresholds of Alg. 1 as the authors ran it (docs/method.md §4)."""

    prompt_frame: int = 0
    box_threshold: float = 0.3
    text_threshold: float = 0.45
    keep_ratio_of_best: float = 0.7
    stage2_box_threshold_min: float = 0.6
    stage2_ratio_of_best: float = 0.85
    stage2_text_threshold_min: float = 0.65
    run_stage2: bool = True
    # The authors' flow (their Grounded-SAM-2 script) by default; the alternatives are
    # named so a run can say which it used.
    # stage2_reprompt: "correct" = a stage-2 box on a frame already tracked corrects it
    #   (SAM2's video predictor: decoded with memory and the frame's previous mask, kept as
    #   a tracked frame); "condition" = a new conditioning frame decoded without memory
    #   (trusts the detector over the memory: every later frame attends to that box).
    stage2_reprompt: str = "correct"
    # stage2_backward: also propagate a stage-2 prompt backward to the start of its run of
    #   empty frames (the authors go forward only, so a run's frames before the first
    #   detection stay empty; backward fills them when the object was only half visible).
    stage2_backward: bool = False
    # empty_rule: a frame is empty when the "first_object"'s mask is (the authors: the first
    #   kept detection in Grounding DINO's query order), or when the "union" of every
    #   object's mask is (one object lost among several then does not count as empty).
    empty_rule: str = "first_object"
    # detection_order: object ids follow Grounding DINO's "query" order (upstream
    #   predict()), or "confidence" (best first); stage-2 boxes pair with the objects in it.
    detection_order: str = "query"

    RANGES: ClassVar[dict] = {
        "prompt_frame": "[0, 1e7]", "box_threshold": "[0, 1]", "text_threshold": "[0, 1]",
        "keep_ratio_of_best": "[0, 1]", "stage2_box_threshold_min": "[0, 1]", "stage2_ratio_of_best": "[0, 1]",
        "stage2_text_threshold_min": "[0, 1]"}
    CHOICES: ClassVar[dict] = {"stage2_reprompt": ("correct", "condition"), "empty_rule": ("first_object", "union"),
                               "detection_order": ("query", "confidence")}

    def __post_init__(self) -> None:
        check_params(self)
        for name, allowed in (("stage2_reprompt", ("correct", "condition")),
                              ("empty_rule", ("first_object", "union")),
                              ("detection_order", ("query", "confidence"))):
            if getattr(self, name) not in allowed:
                raise InputError(f"TwoStageConfig.{name} must be one of {list(allowed)}, got {getattr(self, name)!r}")


@dataclass(frozen=True)
class ScribbleConfig:
    """Sampling of skeleton points; the thresholds are the protocol's."""

    keep_positive_above: float = 0.98
    keep_negative_above: float = 0.995
    seed: int = 0
    # A scribble pixel has some colour channel above this (8-bit images; 0 = any non-zero
    # channel, the protocol's: pure red or blue strokes and anti-aliased edges count).
    binarize_above: int = 0
    # a scribble too short to leave any point still contributes its middle pixel
    at_least_one_per_scribble: bool = True

    RANGES: ClassVar[dict] = {"keep_positive_above": "[0, 1]", "keep_negative_above": "[0, 1]",
                              "seed": "[0, 2147483647]", "binarize_above": "[0, 254]"}

    def __post_init__(self) -> None:
        check_params(self)


# -- mask noise (cobgs.data.mask_noise) ---------------------------------------------------
@dataclass(frozen=True)
class MaskNoiseParams:
    """How often and how strongly masks are corrupted. Rates are probabilities per mask
    (one object in one view).

    Attributes:
        drop_rate: the mask is replaced by an empty one (then nothing else applies).
        morph_rate: the mask is eroded or dilated.
        morph_max_px: the erosion/dilation radius is uniform in 1..morph_max_px pixels.
        dilate_fraction: share of dilations among erosions/dilations.
        jitter_rate: the boundary is jittered.
        jitter_amplitude_px: the largest boundary displacement.
        jitter_scale_px: correlation length of the displacement along the boundary.
        blob_rate: spurious blobs are added.
        blob_count_max: blobs per affected mask, uniform in 1..blob_count_max.
        blob_radius_min_px, blob_radius_max_px: blob disc radius range.
        seed: base seed of every mask's random stream.
    """

    drop_rate: float = 0.05
    morph_rate: float = 0.3
    morph_max_px: int = 3
    dilate_fraction: float = 0.5
    jitter_rate: float = 0.3
    jitter_amplitude_px: float = 2.0
    jitter_scale_px: float = 6.0
    blob_rate: float = 0.2
    blob_count_max: int = 3
    blob_radius_min_px: int = 2
    blob_radius_max_px: int = 5
    seed: int = 0

    RANGES: ClassVar[dict] = {
        "drop_rate": "[0, 1]", "morph_rate": "[0, 1]", "morph_max_px": "[1, 1000]", "dilate_fraction": "[0, 1]",
        "jitter_rate": "[0, 1]", "jitter_amplitude_px": "(0, 1000]", "jitter_scale_px": "(0, 1000]",
        "blob_rate": "[0, 1]", "blob_count_max": "[1, 1000]", "blob_radius_min_px": "[1, 1000]",
        "blob_radius_max_px": "[1, 1000]", "seed": "[0, 2147483647]"}

    def __post_init__(self) -> None:
        check_params(self)
        for name in ("drop_rate", "morph_rate", "dilate_fraction", "jitter_rate", "blob_rate"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0.0 <= v <= 1.0):
                raise InputError(f"MaskNoiseParams.{name} must be a probability in [0, 1], got {v!r}")
        for name in ("morph_max_px", "blob_count_max", "blob_radius_min_px", "blob_radius_max_px"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                raise InputError(f"MaskNoiseParams.{name} must be an int >= 1, got {v!r}")
        if self.blob_radius_max_px < self.blob_radius_min_px:
            raise InputError("MaskNoiseParams.blob_radius_max_px must be >= blob_radius_min_px, "
                             f"got {self.blob_radius_max_px} < {self.blob_radius_min_px}")
        for name in ("jitter_amplitude_px", "jitter_scale_px"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and v > 0):
                raise InputError(f"MaskNoiseParams.{name} must be > 0, got {v!r}")
        if not isinstance(self.seed, int) or self.seed < 0:
            raise InputError(f"MaskNoiseParams.seed must be an int >= 0, got {self.seed!r}")


# -- SfM (cobgs.data.sfm) -----------------------------------------------------------------------
@dataclass(frozen=True)
class SfmOptions:
    """Options of :func:`run_sfm`.

    Attributes:
        matcher: "exhaustive" (every pair), "sequential" (each image with the next
            ``sequential_overlap`` in name order; for ordered captures) or "auto"
            (exhaustive up to ``exhaustive_max_images`` images, sequential above).
        exhaustive_max_images: the "auto" threshold.
        sequential_overlap: neighbours matched per image by the sequential matcher.
        camera_model: COLMAP model fitted during mapping (SIMPLE_RADIAL is COLMAP's default
            for unknown lenses; undistortion turns any model into PINHOLE).
        single_camera: all images share one camera (one capture device).
        camera_params: known intrinsics in ``camera_model``'s parameter order, or None to
            estimate them (from EXIF or a default focal of 1.2 x max(width, height)).
        max_image_size_px: images are downscaled to this longest side for extraction.
        max_num_features: SIFT features kept per image.
        min_num_matches: verified matches a pair needs to join the view graph.
        min_registered_fraction: :class:`DataError` when fewer images register.
        num_threads: CPU threads for every step; 0 = all cores of this machine.
        device: "cpu" or "cuda" (SIFT extraction and matching; mapping is CPU).
        seed: seeds COLMAP's random generator (RANSAC, mapper) for repeatable runs.
        verbose: let COLMAP log INFO lines (otherwise warnings and errors only).
    """

    matcher: str = "auto"
    exhaustive_max_images: int = 150
    sequential_overlap: int = 10
    camera_model: str = "SIMPLE_RADIAL"
    single_camera: bool = True
    camera_params: Optional[Tuple[float, ...]] = None
    max_image_size_px: int = 3200
    max_num_features: int = 8192
    min_num_matches: int = 15
    min_registered_fraction: float = 1.0
    num_threads: int = 0
    device: str = "cpu"
    seed: int = 0
    verbose: bool = False

    RANGES: ClassVar[dict] = {
        "exhaustive_max_images": "[1, 1e6]", "sequential_overlap": "[1, 1e4]", "max_image_size_px": "[1, 1e5]",
        "max_num_features": "[1, 1e7]", "min_num_matches": "[1, 1e6]", "min_registered_fraction": "[0, 1]",
        "num_threads": "[0, 1024]", "seed": "[0, 2147483647]", "camera_params": "[-1e7, 1e7]"}
    CHOICES: ClassVar[dict] = {"matcher": MATCHERS, "device": ("cpu", "cuda")}

    def __post_init__(self) -> None:
        check_params(self)
        if self.matcher not in MATCHERS:
            raise InputError(f"SfmOptions.matcher must be one of {MATCHERS}, got {self.matcher!r}")
        if self.device not in ("cpu", "cuda"):
            raise InputError(f"SfmOptions.device must be 'cpu' or 'cuda', got {self.device!r}")
        if not 0.0 <= self.min_registered_fraction <= 1.0:
            raise InputError("SfmOptions.min_registered_fraction must be in [0, 1], got "
                             f"{self.min_registered_fraction}")
        for name in ("exhaustive_max_images", "sequential_overlap", "max_image_size_px",
                     "max_num_features", "min_num_matches"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                raise InputError(f"SfmOptions.{name} must be a positive int, got {v!r}")
        if not isinstance(self.num_threads, int) or self.num_threads < 0:
            raise InputError(f"SfmOptions.num_threads must be an int >= 0, got {self.num_threads!r}")

    def threads(self) -> int:
        """The thread count actually passed to COLMAP."""
        return self.num_threads or (os.cpu_count() or 1)
