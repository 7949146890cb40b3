"""One entry point that recognises a scene folder's format and reads it."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional, Sequence

from cobgs.errors import DataError
from cobgs.data.scene import Scene


def detect_format(path: os.PathLike | str) -> str:
    """The layout of ``path`` (:data:`cobgs.data.formats.FORMATS`), from the files present."""
    from cobgs.data.formats import detect, layouts_expected

    root = Path(path)
    if not root.is_dir():
        raise DataError("scene folder not found", root)
    found = detect(root)
    if found is not None:
        return found
    raise DataError(f"unrecognised scene layout (expected {layouts_expected()})", root)


def read_scene(
    path: os.PathLike | str,
    *,
    downscale: float = 1.0,
    test_every: int = 8,
    test_names: Optional[Sequence[str]] = None,
    background: Optional[Sequence[float]] = None,
    format: Optional[str] = None,
    distortion: str = "auto",
) -> Scene:
    """Read any supported scene folder (:data:`cobgs.data.formats.FORMATS`).

    Args:
        path: scene folder.
        downscale: divide the image size by this (LLFF: must be an integer with an
            ``images_<k>/`` folder, or ``images/`` is resized).
        test_every: hold out every k-th view (ignored by layouts with their own test split).
        test_names: explicit held-out views (stems or file names).
        background: compositing colour for RGBA images (Blender default: white).
        format: force a reader instead of detecting it.
        distortion: COLMAP scenes: "auto", "undistort" or "ignore" (see
            :func:`cobgs.data.colmap.read_colmap`).
    """
    from cobgs.data.formats import scene_format

    fmt = scene_format(format or detect_format(path), path)
    return fmt.read(path, downscale=downscale, test_every=None if fmt.own_split else test_every,
                    test_names=test_names, background=background, distortion=distortion)
