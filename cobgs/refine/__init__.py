"""Segmentation: COB-GS (labels, scores, boundary split, alternation, RAEM), the peers, results and extraction.

Public names of the modules below are importable from the package too, lazily (importing
``cobgs.refine`` loads nothing heavy).
"""

from __future__ import annotations

from cobgs._lazy import lazy_getattr

_WHERE = {
    'BG_THRESHOLD': 'alternation',
    'FG_THRESHOLD': 'alternation',
    'FlashSplatConfig': 'peers',
    'METHODS': 'peers',
    'MultiObjectResult': 'alternation',
    'PeakMemory': 'result',
    'RefineConfig': 'alternation',
    'RefineResult': 'result',
    'Refiner': 'alternation',
    'SA3DConfig': 'peers',
    'SCORE_EPS': 'scores',
    'ScoreAccumulator': 'scores',
    'StageStats': 'result',
    'apply_raem': 'alternation',
    'boundary_split': 'split',
    'current_rss_bytes': 'result',
    'ensure_label': 'scores',
    'evaluate_masks': 'segment',
    'export_objects': 'segment',
    'export_ply': 'segment',
    'extract': 'segment',
    'flashsplat_votes': 'peers',
    'label_sets': 'segment',
    'make_config': 'peers',
    'mask_loss': 'scores',
    'masks_for': 'alternation',
    'method_threshold': 'segment',
    'nosplit_config': 'peers',
    'object_index': 'segment',
    'pixel_footprint': 'split',
    'pixel_labels_from_mask': 'scores',
    'raem_prune_mask': 'split',
    'refine': 'alternation',
    'refine_objects': 'alternation',
    'refine_scene': 'alternation',
    'render_label_mask': 'scores',
    'render_object_mask': 'segment',
    'render_object_rgb': 'segment',
    'render_removed_rgb': 'segment',
    'restore_pruned': 'result',
    'run_flashsplat': 'peers',
    'run_flashsplat_multi': 'peers',
    'run_method': 'peers',
    'run_nosplit': 'peers',
    'run_sa3d': 'peers',
    'split_candidates': 'split',
    'subset': 'segment',
    'view_scores': 'scores',
    'visible_object_mask': 'segment',
}

__all__ = sorted(_WHERE)

__getattr__ = lazy_getattr(__name__, _WHERE, globals())
