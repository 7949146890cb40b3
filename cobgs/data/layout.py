"""Which layout a scene folder is in: one detector for the readers, ``cobgs new`` and the
dataset stage (standard library only, so ``cobgs new`` stays fast). The layouts and their
markers, in detection order, are :data:`cobgs.data.formats.FORMATS` (the first that matches
wins: ``transforms_train.json`` before ``transforms.json``, a COLMAP model, ``poses_bounds.npy``).
"""

from __future__ import annotations

import os
from typing import Optional

from cobgs.data.formats import COLMAP_MODEL_FILES, colmap_model_dir, detect

__all__ = ["COLMAP_MODEL_FILES", "colmap_model_dir", "detect_layout"]


def detect_layout(root: os.PathLike | str) -> Optional[str]:
    """The name of the layout ``root`` is in (:data:`cobgs.data.formats.FORMATS`), or None."""
    return detect(root)
