"""Workflow-facing copies of the library's config dataclasses.

Every ``cobgs`` command imports all stage modules, and the library configs live in
modules that import torch (several seconds on a loaded machine: a fully cached
``cobgs run`` must stay well under 10 s). So the stages declare these stdlib-only mirrors
as their params and build the library config from them (:func:`to_config`).
tests/stages/test_params.py checks that each mirror has exactly the library's fields and
defaults, so a new library field cannot be silently missing here.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Optional


def to_config(mirror: Any, cls: type, **overrides: Any) -> Any:
    """The library config ``cls`` with the mirror's values (and ``overrides``)."""
    values = dataclasses.asdict(mirror)
    values.update(overrides)
    return cls(**values)


@dataclass(frozen=True)
class TrainOptions:
    """Mirror of :class:`cobgs.train.TrainConfig` (the 3DGS paper's defaults)."""

    iterations: int = 30_000
    seed: int = 0
    scale_schedule: bool = True
    scale_densify_interval: bool = False
    reference_iterations: int = 30_000
    sh_degree: int = 3
    sh_degree_interval_its: int = 1_000
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
    densify_from_its: int = 500
    densify_until_its: int = 15_000
    densify_interval_its: int = 100
    densify_grad_threshold_ndc: float = 2e-4
    dense_scale_fraction: float = 0.01
    split_children: int = 2
    split_scale_divisor: float = 1.6
    prune_min_opacity: float = 0.005
    prune_max_world_scale_fraction: float = 0.1
    prune_max_screen_radius_px: float = 0.0
    max_gaussians: int = 0
    opacity_reset_interval_its: int = 3_000
    opacity_reset_value: float = 0.01
    random_init_points: int = 100_000
    init_opacity: float = 0.1
    background: Optional[tuple[float, float, float]] = None
    random_background: bool = False
    backend: str = "native"
    log_interval_its: int = 10
    checkpoint_interval_its: int = 0


@dataclass(frozen=True)
class RefineOptions:
    """Mirror of :class:`cobgs.refine.RefineConfig` (the released COB-GS behaviour), without
    ``scene_type``: the refine stage sets it (``refine.scene_type``, default: the dataset's)."""

    delta: Optional[float] = None
    mask_stages: Optional[int] = None
    stage_length_views: float = 2.0
    bags: bool = True
    bgtr: bool = True
    raem: str = "released"
    score: str = "count"
    texture_adam: str = "baseline"
    split_size_fraction: float = 0.01
    split_children: int = 2
    split_scale_divisor: float = 1.6
    raem_footprint_px: float = 1.0
    mask_lambda: float = 1.0
    label_lr: float = 0.1
    adam_eps: float = 1e-15
    position_lr: float = 1.6e-6
    sh0_lr: float = 2.5e-3
    shN_lr: float = 2.5e-3 / 20.0
    opacity_lr: float = 0.025
    scaling_lr: float = 5e-3
    rotation_lr: float = 1e-3
    ssim_weight: float = 0.2
    seed: int = 0
    backend: str = "native"
    label_name: str = "mask_logit"
    record_scores: bool = True


@dataclass(frozen=True)
class SA3DOptions:
    """Mirror of :class:`cobgs.peers.SA3DConfig`."""

    lr: float = 1.0
    neg_weight: float = 0.3
    passes: int = 2
    threshold: float = 0.5
    seed: int = 0
    adam_eps: float = 1e-15
    backend: str = "native"


@dataclass(frozen=True)
class FlashSplatOptions:
    """Mirror of :class:`cobgs.peers.FlashSplatConfig`."""

    background_bias: float = 0.0
    backend: str = "native"


@dataclass(frozen=True)
class TwoStageOptions:
    """Mirror of :class:`cobgs.masks.TwoStageConfig` (Alg. 1 thresholds)."""

    prompt_frame: int = 0
    box_threshold: float = 0.3
    text_threshold: float = 0.45
    keep_ratio_of_best: float = 0.7
    stage2_box_threshold_min: float = 0.6
    stage2_ratio_of_best: float = 0.85
    stage2_text_threshold_min: float = 0.65
    stage2_backward: bool = True
    run_stage2: bool = True


@dataclass(frozen=True)
class ScribbleOptions:
    """Mirror of :class:`cobgs.masks.ScribbleConfig` (NVOS point sampling)."""

    keep_positive_above: float = 0.98
    keep_negative_above: float = 0.995
    seed: int = 0
    binarize_above: int = 0
    at_least_one_per_scribble: bool = True


@dataclass(frozen=True)
class MaskNoiseOptions:
    """Mirror of :class:`cobgs.data.mask_noise.MaskNoiseParams`."""

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


@dataclass(frozen=True)
class SfmOptionsParams:
    """Mirror of :class:`cobgs.sfm.SfmOptions` without ``device`` (the workflow's setting)
    and ``verbose`` (COLMAP's own log lines)."""

    matcher: str = "auto"
    exhaustive_max_images: int = 150
    sequential_overlap: int = 10
    camera_model: str = "SIMPLE_RADIAL"
    single_camera: bool = True
    camera_params: Optional[tuple[float, ...]] = None
    max_image_size_px: int = 3200
    max_num_features: int = 8192
    min_num_matches: int = 15
    min_registered_fraction: float = 1.0
    num_threads: int = 0
    seed: int = 0


#: mirror -> (library module, class, fields the mirror leaves out on purpose)
MIRRORS = {
    TrainOptions: ("cobgs.train", "TrainConfig", ()),
    RefineOptions: ("cobgs.refine", "RefineConfig", ("scene_type",)),
    SA3DOptions: ("cobgs.peers", "SA3DConfig", ()),
    FlashSplatOptions: ("cobgs.peers", "FlashSplatConfig", ()),
    TwoStageOptions: ("cobgs.masks.two_stage", "TwoStageConfig", ()),
    ScribbleOptions: ("cobgs.masks.scribbles", "ScribbleConfig", ()),
    MaskNoiseOptions: ("cobgs.data.mask_noise", "MaskNoiseParams", ()),
    SfmOptionsParams: ("cobgs.sfm", "SfmOptions", ("device", "verbose")),
}
