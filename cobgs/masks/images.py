"""Frame loading and the two models' preprocessing (SAM2: stretch to 1024x1024; Grounding DINO: its
own keep-aspect size; ImageNet normalisation)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional, Tuple, Union

import numpy as np

from cobgs.errors import DataError

from cobgs.masks.manifest import Preprocess


def load_rgb(path: Union[str, os.PathLike]) -> np.ndarray:
    """Read an image as RGB uint8 [H, W, 3] (alpha dropped, greyscale expanded)."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            return np.asarray(im.convert("RGB")).copy()
    except (OSError, ValueError, Image.DecompressionBombError) as exc:
        raise DataError(f"cannot read image: {exc}", path) from exc


def to_model_input(rgb: np.ndarray, pre: Preprocess, size_hw: Optional[Tuple[int, int]] = None) -> np.ndarray:
    """Resize and normalise one frame.

    Args:
        rgb: uint8 [H, W, 3] RGB.
        pre: size, interpolation, mean/std, channel order.
        size_hw: the size to resize to (default ``pre.size_hw``: SAM2's stretch; the
            Grounding DINO host passes the frame's keep-aspect size).

    Returns:
        float32 [1, 3, h, w] with (h, w) = ``size_hw``.
    """
    from PIL import Image

    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise DataError(f"frame must be uint8 [H, W, 3], got {rgb.dtype} {list(rgb.shape)}")
    h, w = (int(v) for v in (size_hw or pre.size_hw))
    if rgb.shape[:2] != (h, w):
        # PIL's bicubic matches SAM2's own frame loader (PIL .resize default filter)
        resample = Image.BICUBIC if pre.interpolation == "bicubic" else Image.BILINEAR
        rgb = np.asarray(Image.fromarray(rgb).resize((w, h), resample=resample))
    # One lookup table per channel gives exactly upstream's arithmetic ((v / 255) cast to
    # float32, then (x - mean) / std) at a fraction of the cost on 1024x1024 frames.
    v = (np.arange(256) / 255.0).astype(np.float32)
    order = (0, 1, 2) if pre.rgb else (2, 1, 0)
    out = np.empty((1, 3, h, w), np.float32)
    for dst, src in enumerate(order):
        lut = (v - np.float32(pre.mean[src])) / np.float32(pre.std[src])
        np.take(lut, rgb[..., src], out=out[0, dst])
    return out


def image_size(path: Union[str, os.PathLike]) -> Tuple[int, int]:
    """(height, width) of an image file without decoding the pixels."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            return im.size[1], im.size[0]
    except (OSError, ValueError, Image.DecompressionBombError) as exc:
        raise DataError(f"cannot read image: {exc}", Path(path)) from exc
