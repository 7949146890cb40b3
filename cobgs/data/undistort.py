"""Undistortion of distorted camera models to PINHOLE through pycolmap.

The rasterizer models an ideal pinhole, so images (and their masks) taken with a
distorted model are resampled once, at load time, onto the PINHOLE camera that
pycolmap's undistorter chooses (the camera ``colmap image_undistorter`` would write),
with the same inverse mapping, in float32.
"""

from __future__ import annotations

import os
from typing import Sequence

import cv2
import numpy as np

from cobgs.errors import DataError

# Models whose pixels are already pinhole: only re-expressed, never resampled.
PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")


# Models whose parameters start with a pinhole's (f, cx, cy or fx, fy, cx, cy): how many
# focal lengths they hold. The distortion terms follow.
_FOCALS = {"SIMPLE_PINHOLE": 1, "PINHOLE": 2, "SIMPLE_RADIAL": 1, "RADIAL": 1, "OPENCV": 2,
           "FULL_OPENCV": 2}
# Of those, the distorted ones: these can be read as their pinhole with the distortion dropped.
DROPPABLE_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")


def split_pinhole(model: str, params: Sequence[float]
                  ) -> tuple[tuple[float, float, float, float], list[float]]:
    """((fx, fy, cx, cy), the distortion terms after them) of a camera whose parameters
    start with a pinhole's: PINHOLE / SIMPLE_PINHOLE (no terms), SIMPLE_RADIAL / RADIAL /
    OPENCV / FULL_OPENCV (read as a pinhole, the terms returned)."""
    n = _FOCALS.get(model)
    if n is None:
        raise DataError(f"camera model {model} does not start with pinhole parameters")
    vals = [float(v) for v in params]
    fx, fy = (vals[0], vals[0]) if n == 1 else (vals[0], vals[1])
    return (fx, fy, vals[n], vals[n + 1]), vals[n + 2:]


def pinhole_params(model: str, params: Sequence[float]) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) of a PINHOLE or SIMPLE_PINHOLE camera."""
    if model not in PINHOLE_MODELS:
        raise DataError(f"camera model {model} is not a pinhole model")
    return split_pinhole(model, params)[0]


def undistort_view_arrays(
    image: np.ndarray,  # [H, W, C] float32 in [0, 1]
    masks: dict[str, np.ndarray],  # object → [H, W] float32 binary
    model: str,
    params: Sequence[float],
    width: int,
    height: int,
    path: os.PathLike | str,
) -> tuple[np.ndarray, dict[str, np.ndarray], tuple[float, float, float, float, int, int]]:
    """Undistort one image and its masks to a PINHOLE camera with pycolmap.

    Args:
        image: [H, W, C] float32 pixels in [0, 1] (C = 1, 3 or 4).
        masks: object name → [H, W] binary float32 mask at the same size.
        model: COLMAP camera model name (e.g. "OPENCV", "SIMPLE_RADIAL").
        params: the model's parameters in COLMAP order.
        width, height: image size the parameters refer to.
        path: image file, for error messages.

    Returns:
        (undistorted image [H', W', C] float32, undistorted binary masks [H', W'],
        (fx, fy, cx, cy, W', H') of the PINHOLE output camera).
    """
    from cobgs.data.pycolmap_import import import_pycolmap

    pycolmap = import_pycolmap()

    try:
        cam = pycolmap.Camera.create_from_model_name(1, model, 1.0, int(width), int(height))
        cam.params = [float(p) for p in params]
    except Exception as e:  # pycolmap raises plain RuntimeError/ValueError here
        raise DataError(f"unknown or invalid camera model {model!r} with params {list(params)}: {e}", path) from e
    opts = pycolmap.UndistortCameraOptions()
    out_cam = pycolmap.undistort_camera(opts, cam)

    # Inverse warp, as COLMAP's undistorter does: each output pixel centre is unprojected
    # with the PINHOLE camera and re-projected with the distorted one; sampling is
    # bilinear in float32 (COLMAP pixel centres sit at +0.5, OpenCV's at integers).
    W, H = int(out_cam.width), int(out_cam.height)
    u, v = np.meshgrid(np.arange(W, dtype=np.float64) + 0.5, np.arange(H, dtype=np.float64) + 0.5)
    rays = out_cam.cam_from_img(np.stack([u.ravel(), v.ravel()], 1))
    src = cam.img_from_cam(np.concatenate([rays, np.ones((rays.shape[0], 1))], 1), False)
    map_x = (src[:, 0] - 0.5).reshape(H, W).astype(np.float32)
    map_y = (src[:, 1] - 0.5).reshape(H, W).astype(np.float32)

    def warp(arr: np.ndarray) -> np.ndarray:
        out = cv2.remap(
            np.ascontiguousarray(arr, np.float32), map_x, map_y, cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT, borderValue=0,
        )
        return out.reshape(H, W, -1) if arr.ndim == 3 else out

    out_image = warp(image)
    out_masks = {k: (warp(m) >= 0.5).astype(np.float32) for k, m in masks.items()}
    fx, fy, cx, cy = pinhole_params(out_cam.model.name, list(out_cam.params))
    return out_image, out_masks, (fx, fy, cx, cy, int(out_cam.width), int(out_cam.height))
