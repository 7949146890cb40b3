"""Evaluation: metrics (IoU, accuracy, boundary IoU, PSNR, SSIM) and the protocols.

Public names of the modules below are importable from the package too, lazily (importing
``cobgs.evaluate`` loads nothing heavy).
"""

from __future__ import annotations

from cobgs._lazy import lazy_getattr

_WHERE = {
    'MaskScores': 'protocols',
    'ORACLE_METHOD': 'protocols',
    'accuracy': 'metrics',
    'aggregate': 'protocols',
    'binarize': 'metrics',
    'bootstrap_mean_diff': 'protocols',
    'boundary_iou': 'metrics',
    'boundary_width': 'metrics',
    'compare_masks': 'protocols',
    'exact_scores': 'protocols',
    'iou': 'metrics',
    'lerf_prompt_scores': 'protocols',
    'lerf_summary': 'protocols',
    'mask_boundary': 'metrics',
    'nanmean': 'protocols',
    'nvos_summary': 'protocols',
    'oracle_choice': 'protocols',
    'psnr': 'metrics',
    'psnr_scores': 'protocols',
    'read_mask_u8': 'protocols',
    'resize_nearest': 'protocols',
    'ssim': 'metrics',
    'to_u8': 'protocols',
    'visible_object_mask': 'protocols',
}

__all__ = sorted(_WHERE)

__getattr__ = lazy_getattr(__name__, _WHERE, globals())
