"""Evaluation metrics: PSNR, SSIM for images; IoU, accuracy, boundary IoU for masks.

Mask metrics follow docs/method.md §5: masks are binary arrays of the same size (binarise and
resize before calling; :func:`binarize` does the "> 128 of 255" rule); IoU = TP / (TP +
FP + FN), accuracy = (TP + TN) / pixels, boundary IoU compares the inner boundaries
``mask − erode(mask)`` with a 3x3 kernel applied d = max(1, round(0.02 · diagonal))
times after a one-pixel zero pad (so the image border counts as background).
When both masks are empty (no union), IoU and boundary IoU are 1.0: the prediction
agrees perfectly with an empty ground truth; protocols that skip empty ground truths
must do so before calling.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import torch
from torch import Tensor

from cobgs.errors import InputError
from cobgs.evaluate.ssim import ssim as _ssim


def psnr(img: Tensor, ref: Tensor, max_value: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB of one image ([H, W, C], values in [0, max]).

    Returns ``inf`` for identical images.
    """
    if img.shape != ref.shape:
        raise InputError(f"img and ref must have the same shape, got {list(img.shape)} and {list(ref.shape)}")
    mse = torch.mean((img.detach().double() - ref.detach().double()) ** 2).item()
    if mse == 0.0:
        return math.inf
    return 10.0 * math.log10(max_value**2 / mse)


def ssim(img: Tensor, ref: Tensor) -> float:
    """Mean SSIM of one image pair ([H, W, C] in [0, 1]); 3DGS's Gaussian-window SSIM."""
    with torch.no_grad():
        return float(_ssim(img.detach().float(), ref.detach().float()))


def _as_bool(mask, name: str) -> np.ndarray:
    if isinstance(mask, Tensor):
        mask = mask.detach().cpu().numpy()
    arr = np.asarray(mask)
    if arr.ndim != 2:
        raise InputError(f"{name} must be a 2D [H, W] mask, got shape {list(arr.shape)}")
    if arr.dtype != np.bool_:
        raise InputError(f"{name} must be boolean (binarise first, e.g. with binarize()), got {arr.dtype}")
    return arr


def _pair(pred, gt) -> tuple[np.ndarray, np.ndarray]:
    p, g = _as_bool(pred, "pred"), _as_bool(gt, "gt")
    if p.shape != g.shape:
        raise InputError(f"pred and gt must have the same shape, got {list(p.shape)} and {list(g.shape)}")
    return p, g


def binarize(mask, threshold: float = 128) -> np.ndarray:
    """``mask > threshold`` as a bool array (8-bit masks: > 128 as in the NVOS protocol)."""
    if isinstance(mask, Tensor):
        mask = mask.detach().cpu().numpy()
    return np.asarray(mask) > threshold


def iou(pred, gt) -> float:
    """Intersection over union of two [H, W] bool masks (1.0 when both are empty)."""
    p, g = _pair(pred, gt)
    union = np.logical_or(p, g).sum()
    if union == 0:
        return 1.0
    return float(np.logical_and(p, g).sum() / union)


def accuracy(pred, gt) -> float:
    """Fraction of pixels where two [H, W] bool masks agree."""
    p, g = _pair(pred, gt)
    return float((p == g).mean())


def boundary_width(height: int, width: int, ratio: float = 0.02) -> int:
    """d = max(1, round(ratio · image diagonal)) erosion iterations."""
    return max(1, int(round(ratio * math.hypot(height, width))))


def mask_boundary(mask, ratio: float = 0.02) -> np.ndarray:
    """Inner boundary band of a [H, W] bool mask: mask minus its d-fold 3x3 erosion.

    The one-pixel zero pad makes pixels at the image border boundary pixels too.
    """
    m = _as_bool(mask, "mask")
    h, w = m.shape
    d = boundary_width(h, w, ratio)
    padded = cv2.copyMakeBorder(m.astype(np.uint8), 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=0)
    eroded = cv2.erode(padded, np.ones((3, 3), np.uint8), iterations=d)[1 : h + 1, 1 : w + 1]
    return m & ~eroded.astype(bool)


def boundary_iou(pred, gt, ratio: float = 0.02) -> float:
    """Boundary IoU |Bg ∩ Bp| / |Bg ∪ Bp| of two [H, W] bool masks (1.0 when both empty)."""
    p, g = _pair(pred, gt)
    bp, bg = mask_boundary(p, ratio), mask_boundary(g, ratio)
    union = np.logical_or(bp, bg).sum()
    if union == 0:
        return 1.0
    return float(np.logical_and(bp, bg).sum() / union)
