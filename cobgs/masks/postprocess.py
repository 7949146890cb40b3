"""Small numeric helpers around the SAM2 graphs: mask choice, resizing, hole filling.

All follow the released SAM2 video predictor's host-side behaviour (see the contract).
"""

from __future__ import annotations

from typing import Tuple

import numpy as np

NO_OBJ_SCORE = -1024.0  # logit SAM2 writes where the object is predicted absent


def resize_logits(logits: np.ndarray, hw: Tuple[int, int]) -> np.ndarray:
    """Bilinear resize of float32 [h, w] logits to ``hw``, half-pixel centres.

    cv2's INTER_LINEAR on float32 samples at half-pixel centres without antialiasing,
    which is torch's ``interpolate(mode="bilinear", align_corners=False)``.
    """
    import cv2

    h, w = int(hw[0]), int(hw[1])
    if logits.shape == (h, w):
        return logits
    return cv2.resize(np.ascontiguousarray(logits, np.float32), (w, h),
                      interpolation=cv2.INTER_LINEAR)


def stability_score(logits: np.ndarray, delta: float) -> float:
    """area(logits > delta) / area(logits > -delta); 1 when the union is empty."""
    inter = np.count_nonzero(logits > delta)
    union = np.count_nonzero(logits > -delta)
    return float(inter) / float(union) if union > 0 else 1.0


def choose_mask(
    masks: np.ndarray,
    ious: np.ndarray,
    multimask: bool,
    stability_delta: float,
    stability_thresh: float,
    multimask_token_for_ptr: bool = True,
) -> Tuple[int, int]:
    """Pick the output mask plane and the plane whose object pointer is kept.

    Args:
        masks: float32 [4, 256, 256] logits for tokens 0..3 (before no-object gating).
        ious: float32 [4] predicted IoUs.
        multimask: True on propagated frames and for at most one real point; False for a
            box or two or more points.

    Returns:
        (mask_plane, pointer_plane). Multimask: argmax IoU over tokens 1..3, and that
        token's pointer. Single mask: token 0 unless its stability score is below the
        threshold, then the best of 1..3; the pointer stays token 0.
    """
    if masks.shape[0] == 1:  # the export baked its own choice in
        return 0, 0
    offset = 1 if masks.shape[0] == 4 else 0  # 3 planes: multimask tokens only
    best = offset + int(np.argmax(ious[offset:]))
    if multimask or offset == 0:
        return best, (best if multimask_token_for_ptr else 0)
    if stability_score(masks[0], stability_delta) >= stability_thresh:
        return 0, 0
    return best, 0


def fill_holes(logits: np.ndarray, max_area: int) -> np.ndarray:
    """Set background components (logit <= 0, 8-connected) of area <= max_area to 0.1.

    Args:
        logits: float32 [h, w] low-resolution mask logits.

    Returns:
        a new array (the input is not modified).
    """
    import cv2

    if max_area <= 0:
        return logits
    bg = (logits <= 0).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(bg, connectivity=8)
    if n <= 1:
        return logits
    small = np.zeros(n, bool)
    small[1:] = stats[1:, cv2.CC_STAT_AREA] <= max_area
    if not small.any():
        return logits
    out = logits.copy()
    out[small[labels]] = 0.1  # upstream fills with a small positive score
    return out


def round_bfloat16(x: np.ndarray) -> np.ndarray:
    """Round float32 values to bfloat16 precision (nearest even), kept as float32."""
    u = np.ascontiguousarray(x, np.float32).view(np.uint32)
    rounded = u + np.uint32(0x7FFF) + ((u >> np.uint32(16)) & np.uint32(1))
    return (rounded & np.uint32(0xFFFF0000)).view(np.float32)


def sine_pe_1d(pos: np.ndarray, dim: int, temperature: float = 10000.0) -> np.ndarray:
    """Transformer sine encoding of scalar positions: [n] -> float32 [n, dim] (sin | cos)."""
    half = dim // 2
    k = np.arange(half, dtype=np.float32)
    dim_t = np.float32(temperature) ** (2 * (k // 2) / np.float32(half))
    arg = pos.astype(np.float32)[:, None] / dim_t.astype(np.float32)
    return np.concatenate([np.sin(arg), np.cos(arg)], axis=1).astype(np.float32)
