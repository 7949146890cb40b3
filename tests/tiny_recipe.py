"""The short training recipe the end-to-end tests share (tests/ is on sys.path).

A 160x120 synthetic scene of 16 views trains to a usable baseline in a few hundred
iterations with this schedule; COLMAP runs on one thread (with two it is not repeatable:
held-out IoUs moved between 0.78 and 0.95 from run to run).
"""

from __future__ import annotations


def tiny_recipe(iterations: int = 500, densify_until_its: int = 350, sfm: str = "always",
                stage_length_views: float = 2.0, mask_stages: int = 3) -> str:
    """``[params.sfm]``, ``[params.train]`` and ``[params.refine.cobgs]`` TOML tables."""
    sfm_text = f'[params.sfm]\nmode = "{sfm}"\n'
    if sfm != "never":
        sfm_text += '\n[params.sfm.options]\ncamera_model = "SIMPLE_PINHOLE"\nnum_threads = 1\n'
    return f"""{sfm_text}
[params.train]
iterations = {iterations}
scale_schedule = false
densify_from_its = 50
densify_until_its = {densify_until_its}
densify_interval_its = 50
opacity_reset_interval_its = 1000
position_lr_decay_its = {iterations}
sh_degree_interval_its = 100
max_gaussians = 6000

[params.refine.cobgs]
stage_length_views = {stage_length_views}
mask_stages = {mask_stages}
"""
