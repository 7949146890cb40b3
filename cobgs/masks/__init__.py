"""Mask generation through ONNX exports of SAM2 (video) and Grounding DINO.

Public entry points (imported lazily so ``import cobgs.masks`` stays light):

* :func:`generate_masks` — text prompt, two-stage (paper Alg. 1);
* :func:`generate_masks_from_scribbles` — NVOS scribbles -> points -> SAM2;
* :func:`generate_masks_from_points` — points / box on one frame -> SAM2;
* :func:`generate_masks_from_clicks` — clicks on several frames -> SAM2 (:func:`read_clicks`
  reads click files: SAGA-v2's NVOS points or the per-object layout);
* :class:`ModelsNotConfiguredError`, :class:`NoDetectionError`, :class:`TwoStageConfig`,
  :class:`ScribbleConfig`, :class:`RunOptions`, :func:`load_manifest`.
"""

from __future__ import annotations

_LAZY = {
    "generate_masks": "api",
    "generate_masks_from_points": "api",
    "generate_masks_from_clicks": "api",
    "FramePrompt": "api",
    "read_clicks": "clicks",
    "generate_masks_from_scribbles": "api",
    "MaskGenerationResult": "api",
    "ModelsNotConfiguredError": "manifest",
    "load_manifest": "manifest",
    "NoDetectionError": "two_stage",
    "TwoStageConfig": "two_stage",
    "ScribbleConfig": "scribbles",
    "RunOptions": "session",
}

__all__ = sorted(_LAZY)


def __getattr__(name):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module 'cobgs.masks' has no attribute {name!r}")
