"""One entry point that recognises a scene folder's format and reads it."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional, Sequence

from cobgs.errors import DataError
from cobgs.data.scene import Scene


def detect_format(path: os.PathLike | str) -> str:
    """"blender", "transforms", "colmap" or "llff", from the files present in ``path``."""
    from cobgs.data.layout import detect_layout

    root = Path(path)
    if not root.is_dir():
        raise DataError("scene folder not found", root)
    found = detect_layout(root)
    if found is not None:
        return found
    raise DataError(
        "unrecognised scene layout (expected transforms_train.json, transforms.json, a "
        "COLMAP model in sparse/0/, or poses_bounds.npy)",
        root,
    )


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
    """Read any supported scene folder.

    Args:
        path: scene folder.
        downscale: divide the image size by this (LLFF: must be an integer with an
            ``images_<k>/`` folder, or ``images/`` is resized).
        test_every: hold out every k-th view (ignored by Blender scenes, which have
            their own test split).
        test_names: explicit held-out views (stems or file names).
        background: compositing colour for RGBA images (Blender default: white).
        format: force a reader instead of detecting it.
        distortion: COLMAP scenes: "auto", "undistort" or "ignore" (see
            :func:`cobgs.data.colmap.read_colmap`).
    """
    fmt = format or detect_format(path)
    if fmt == "blender":
        from cobgs.data.blender import read_blender

        if test_names is not None:
            raise DataError("Blender scenes use transforms_test.json; test_names is not supported", path)
        kw = {} if background is None else {"background": background}
        return read_blender(path, downscale=downscale, **kw)
    if fmt == "transforms":
        from cobgs.data.transforms import read_transforms

        kw = {} if background is None else {"background": background}
        return read_transforms(path, downscale=downscale, test_every=test_every, test_names=test_names, **kw)
    if fmt == "colmap":
        from cobgs.data.colmap import read_colmap

        return read_colmap(path, downscale=downscale, test_every=test_every, test_names=test_names,
                           distortion=distortion)
    if fmt == "llff":
        from cobgs.data.llff import read_llff

        k = int(round(downscale))
        if abs(downscale - k) > 1e-9:
            raise DataError(f"LLFF downscale must be an integer, got {downscale}", path)
        return read_llff(path, downscale=k, test_every=test_every, test_names=test_names)
    raise DataError(f"unknown scene format {fmt!r} (expected blender, transforms, colmap, llff)", path)
