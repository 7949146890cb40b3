"""Which layout a scene folder is in: one detector for the readers, ``cobgs new`` and the
dataset stage (standard library only, so ``cobgs new`` stays fast).

Order (the first that matches wins): ``transforms_train.json`` (NeRF-synthetic / Blender:
its train / test split is part of the data), ``transforms.json`` (instant-ngp, nerfstudio),
a COLMAP model (``sparse/0``, ``sparse`` or the folder itself: cameras, images and points3D
as ``.bin`` or ``.txt``), ``poses_bounds.npy`` (LLFF).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional

COLMAP_MODEL_FILES = ("cameras", "images", "points3D")


def colmap_model_dir(root: os.PathLike | str) -> Optional[Path]:
    """The folder holding a complete COLMAP model under ``root``, or None."""
    root = Path(root)
    for cand in (root / "sparse" / "0", root / "sparse", root):
        for ext in (".bin", ".txt"):
            if all((cand / f"{n}{ext}").is_file() for n in COLMAP_MODEL_FILES):
                return cand
    return None


def detect_layout(root: os.PathLike | str) -> Optional[str]:
    """"blender", "transforms", "colmap" or "llff" (module docstring), or None."""
    root = Path(root)
    if (root / "transforms_train.json").is_file():
        return "blender"
    if (root / "transforms.json").is_file():
        return "transforms"
    if colmap_model_dir(root) is not None:
        return "colmap"
    if (root / "poses_bounds.npy").is_file():
        return "llff"
    return None
