"""The baseline training's config, its recipes and its resolved schedule (cobgs.train)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar, Optional

from cobgs.errors import InputError

from .checks import check_params


# -- baseline training (cobgs.train.optimize) ---------------------------------------------------------
RECIPES_NAMES = ("3dgs", "fast")  # (the recipes' values: RECIPES, below the class)
@dataclass(frozen=True)
class TrainConfig:
    """Every knob of the baseline optimisation (defaults: the 3DGS paper's)."""

    iterations: Optional[int] = field(default=None, metadata={"help": (
        "unset: the recipe's (3dgs: the paper's 30 000; fast: 12 000), as `cobgs new` leaves it; "
        "workflows/shared_data.toml sets 7000, the 3DGS short schedule (compressed by scale_schedule)")})
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
    # Densification that does not depend on the render size (issue 57). densify_grad_rescale: the
    # view-space gradient of a render at 1/d counts d times (a coarse render's gradients are
    # smaller: fewer Gaussians cross 3DGS's 2e-4 threshold while the renders are small, and the
    # run ends with fewer). budget_schedule "resolution": the budget's count grows with the
    # share of full-resolution pixels rendered (1/d^2; all of it once the renders are full
    # size), DashGaussian's primitive schedule, instead of the line over the iterations.
    densify_grad_rescale: bool = field(default=False, metadata={"before": False})
    # densify_stats_every k > 0 (issue 57 item 2, the other half): the statistics are gathered at
    # full resolution only. While the resolution schedule renders below full size inside the
    # densification window, every k-th step renders its view at full size, and only those steps
    # feed the densification statistics (gradient, visibility count, screen radius); the others
    # train at their small size and add nothing. Once the renders are full size every step feeds
    # them, as 3DGS. k at most densify_interval_its, so each densification step has samples.
    densify_stats_every: int = field(default=0, metadata={"before": 0})
    budget_schedule: str = field(default="line", metadata={"before": "line"})
    # A budget that follows the scene (issue 57 item 3). budget_schedule "growth": until
    # budget_probe_at of the densification window, 3DGS's own rule densifies (no ceiling); the
    # count it grew to there, extrapolated linearly over the whole window, becomes the budget
    # (at least the count reached), and the line runs from there to it at budget_full_at.
    # budget_edge_exempt k > 0: a Gaussian whose averaged gradient is at least k x 3DGS's
    # threshold (the strongest edges) densifies even where the ceiling leaves no room.
    budget_probe_at: float = field(default=0.25, metadata={"before": 0.25})
    # Where the growth is measured from. "start": from the initial count at the window's start
    # (the rule measured first). "trough": from the fewest Gaussians seen in the window so far
    # (a random-box start prunes most of its box first, so its count falls before it grows;
    # measured from the start, that fall reads as no growth), over a span of budget_probe_at
    # of the window after that point, extrapolated to the window's end. With no fall the two
    # are the same rule.
    budget_probe_from: str = field(default="start", metadata={"before": "start"})
    budget_edge_exempt: float = field(default=0.0, metadata={"before": 0.0})
    # Full-resolution random crops instead of whole frames late in the run (issue 57 item 4):
    # once densification has ended and the renders are full size, each step renders and fits a
    # random crop of crop_fraction of each side of the frame (1: whole frames, as 3DGS).
    crop_fraction: float = field(default=1.0, metadata={"before": 1.0})
    # Stop once the training loss has flattened (issue 57 item 4): after densification has ended
    # and the renders are full size, the mean loss of each window of plateau_window_its iterations
    # is compared with the previous window's; a relative gain below stop_at_plateau ends the run
    # (train.json records where). 0: run every iteration, as 3DGS.
    stop_at_plateau: float = field(default=0.0, metadata={"before": 0.0})
    plateau_window_its: int = field(default=500, metadata={"before": 500})
    # The rasterizer of the training steps (issue 60): "ours" (cobgs.render), or "gsplat" (its
    # ``rasterization``, CUDA only, an optional extra: `pip install gsplat`), for users who trust
    # gsplat and for measuring ours against it on the same trainer, data and schedule. Evaluation,
    # refinement and label counts stay ours. Refused, in one line, where gsplat is not importable.
    rasterizer: str = field(default="ours", metadata={"before": "ours"})
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
        "budget_full_at": "(0, 1]", "stop_at_plateau": "[0, 1]", "plateau_window_its": "[10, 1e6]",
        "budget_probe_at": "(0, 1)", "budget_edge_exempt": "[0, 1e6]", "crop_fraction": "[0.05, 1]",
        "densify_stats_every": "[0, 1e7]",
    }
    CHOICES: ClassVar[dict] = {"backend": ("native", "reference"), "recipe": tuple(RECIPES_NAMES),
                               "budget_schedule": ("line", "resolution", "growth"), "rasterizer": ("ours", "gsplat"),
                               "budget_probe_from": ("start", "trough")}

    def __post_init__(self):
        check_params(self)
        if self.rasterizer == "gsplat":  # (importable is all this torch-free module can check; the device: Trainer)
            import importlib.util

            if importlib.util.find_spec("gsplat") is None:
                raise InputError("TrainConfig.rasterizer = 'gsplat' needs gsplat, which is not installed "
                                 "(pip install gsplat, on a machine with CUDA); 'ours' needs nothing more")
        for name, value in RECIPES[self.recipe].items():  # what the caller left unset: the recipe's
            if getattr(self, name) is None:
                object.__setattr__(self, name, value)
        interval = self.schedule().densify_interval
        if self.densify_stats_every > interval:
            raise InputError(
                f"TrainConfig.densify_stats_every = {self.densify_stats_every} is more than the "
                f"densification interval ({interval} iterations): some densification steps would "
                f"have no full-size samples; expected 0 (off) or 1 .. {interval}")

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




@dataclass(frozen=True)
class Schedule:
    """Resolved iteration counts of one run (see :meth:`TrainConfig.schedule`)."""

    sh_degree_interval: int
    position_lr_decay: int
    densify_from: int
    densify_until: int
    densify_interval: int
    opacity_reset_interval: int


