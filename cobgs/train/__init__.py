"""The Gaussians and their optimisation: the model, PLY I/O, losses, Adam state, the 3DGS training loop.

Public names of the modules below are importable from the package too, lazily (importing
``cobgs.train`` loads nothing heavy).
"""

from __future__ import annotations

from cobgs._lazy import lazy_getattr

_WHERE = {
    'CHECKPOINT_VERSION': 'optimize',
    'CORE': 'gaussians',
    'GaussianModel': 'gaussians',
    'MOMENTS_FILE': 'adam_moments',
    'SSIM_C1': 'losses',
    'SSIM_C2': 'losses',
    'SSIM_SIGMA': 'losses',
    'SSIM_WINDOW': 'losses',
    'TrainResult': 'optimize',
    'Trainer': 'optimize',
    'check_extra_name': 'gaussians',
    'check_model_finite': 'optimize',
    'evaluate': 'optimize',
    'expon_lr': 'optimize',
    'export_moments': 'adam_moments',
    'gaussian_lrs': 'gaussians',
    'initial_model': 'optimize',
    'inverse_sigmoid': 'gaussians',
    'knn_mean_sq_dist': 'gaussians',
    'l1_loss': 'losses',
    'load_model': 'optimize',
    'load_moments': 'adam_moments',
    'load_ply': 'ply',
    'peak_rss_bytes': 'optimize',
    'photometric_loss': 'losses',
    'quat_to_rotmat': 'gaussians',
    'read_moments': 'adam_moments',
    'save_atomic': 'optimize',
    'save_moments': 'adam_moments',
    'save_ply': 'ply',
    'ssim': 'losses',
    'ssim_map': 'losses',
    'train': 'optimize',
}

__all__ = sorted(_WHERE)

__getattr__ = lazy_getattr(__name__, _WHERE, globals())
