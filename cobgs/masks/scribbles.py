"""NVOS scribbles -> SAM2 point prompts (docs/method.md §5).

Each scribble image is binarised (a scribble pixel is any pixel with a non-zero colour
channel, as the reference methods read them: pure red or blue strokes count) and
skeletonised (scikit-image); a skeleton pixel is kept
as a positive point where U(0,1) > 0.98 and as a negative point where U(0,1) > 0.995, with
one seeded generator drawn over the positive scribbles first, then the negative ones.
Scribbles come at their own resolution (1/4 of the full images in NVOS) and are mapped
onto the reference frame's pixels.
"""

from __future__ import annotations

import os
from typing import Sequence, Tuple, Union

import numpy as np

from cobgs.configs import ScribbleConfig
from cobgs.errors import DataError, InputError

PathLike = Union[str, os.PathLike]


def _load_scribble(path: PathLike, threshold: int) -> np.ndarray:
    """bool [H, W]: pixels with some colour channel above ``threshold``; where the image has
    transparency, fully transparent pixels are never part of the scribble."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            transparent = im.mode in ("RGBA", "LA", "PA") or \
                (im.mode == "P" and "transparency" in im.info)
            a = np.asarray(im.convert("RGBA" if transparent else "RGB"))
    except (OSError, ValueError, Image.DecompressionBombError) as exc:
        raise DataError(f"cannot read scribble: {exc}", path) from exc
    mask = (a[..., :3] > threshold).any(axis=-1)
    if transparent:
        mask &= a[..., 3] > 0
    return mask


def skeleton_points(mask: np.ndarray) -> np.ndarray:
    """int [n, 2] (row, col) of the skeleton pixels of a bool [H, W] scribble, row-major."""
    from skimage.morphology import skeletonize

    return np.argwhere(skeletonize(mask))


def scribble_points(
    positive: Sequence[PathLike],
    negative: Sequence[PathLike],
    frame_hw: Tuple[int, int],
    config: ScribbleConfig = ScribbleConfig(),
) -> Tuple[np.ndarray, np.ndarray]:
    """Sample point prompts from scribble images.

    Args:
        positive, negative: scribble image paths (any resolution, same for all).
        frame_hw: (height, width) of the frame the points are for.

    Returns:
        (points float32 [n, 2] as (x, y) frame pixels, labels int32 [n] 1/0).
    """
    if not positive:
        raise InputError("NVOS prompting needs at least one positive scribble")
    rng = np.random.default_rng(config.seed)
    pts, labs = [], []
    for paths, thresh, label in ((positive, config.keep_positive_above, 1),
                                 (negative, config.keep_negative_above, 0)):
        for p in paths:
            mask = _load_scribble(p, config.binarize_above)
            sk = skeleton_points(mask)
            if sk.shape[0] == 0:
                raise DataError("scribble has no foreground pixel", p)
            keep = sk[rng.random(sk.shape[0]) > thresh]
            if keep.shape[0] == 0 and config.at_least_one_per_scribble:
                keep = sk[sk.shape[0] // 2][None]
            sy = frame_hw[0] / mask.shape[0]
            sx = frame_hw[1] / mask.shape[1]
            # pixel centres map onto pixel centres across resolutions
            xy = np.stack([(keep[:, 1] + 0.5) * sx - 0.5, (keep[:, 0] + 0.5) * sy - 0.5], 1)
            pts.append(xy.astype(np.float32))
            labs.append(np.full(keep.shape[0], label, np.int32))
    return np.concatenate(pts), np.concatenate(labs)
