"""Host-side numerics: hole filling, mask choice, resizing, bfloat16 rounding."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from cobgs.masks.postprocess import (choose_mask, fill_holes, resize_logits, round_bfloat16,
                                     stability_score)
from cobgs.masks.video import _scaled_sigmoid


def _holes_reference(logits, max_area):
    """Flood fill (8-connected) of background components, written plainly."""
    bg = logits <= 0
    seen = np.zeros_like(bg)
    out = logits.copy()
    h, w = bg.shape
    for sy in range(h):
        for sx in range(w):
            if not bg[sy, sx] or seen[sy, sx]:
                continue
            stack, comp = [(sy, sx)], []
            seen[sy, sx] = True
            while stack:
                y, x = stack.pop()
                comp.append((y, x))
                for dy in (-1, 0, 1):
                    for dx in (-1, 0, 1):
                        yy, xx = y + dy, x + dx
                        if 0 <= yy < h and 0 <= xx < w and bg[yy, xx] and not seen[yy, xx]:
                            seen[yy, xx] = True
                            stack.append((yy, xx))
            if len(comp) <= max_area:
                for y, x in comp:
                    out[y, x] = 0.1
    return out


def test_fill_holes_matches_flood_fill():
    rng = np.random.default_rng(1)
    logits = rng.standard_normal((40, 40)).astype(np.float32) + 0.8
    np.testing.assert_array_equal(fill_holes(logits, 8), _holes_reference(logits, 8))
    # a 3x3 hole (9 px) stays, a 2x4 hole (8 px) is filled; diagonal pixels connect
    m = np.full((20, 20), 5.0, np.float32)
    m[2:5, 2:5] = -1
    m[10:12, 10:14] = -1
    m[15, 15] = m[16, 16] = -1  # one 2-pixel component through the diagonal
    out = fill_holes(m, 8)
    assert (out[2:5, 2:5] == -1).all() and (out[10:12, 10:14] == 0.1).all()
    assert out[15, 15] == 0.1 and out[16, 16] == 0.1
    assert fill_holes(m, 0) is m


def test_stability_and_choice():
    planes = np.zeros((4, 10, 10), np.float32)
    planes[0] = 1.0  # stable: every pixel above +delta
    ious = np.array([0.1, 0.2, 0.9, 0.3], np.float32)
    assert stability_score(planes[0], 0.05) == 1.0
    assert choose_mask(planes, ious, multimask=True, stability_delta=0.05,
                       stability_thresh=0.98) == (2, 2)
    assert choose_mask(planes, ious, False, 0.05, 0.98) == (0, 0)
    planes[0, :5] = 0.01  # half the pixels in (-delta, +delta]: stability 0.5
    assert stability_score(planes[0], 0.05) == pytest.approx(0.5)
    assert choose_mask(planes, ious, False, 0.05, 0.98) == (2, 0)  # pointer stays token 0
    assert choose_mask(planes, ious, True, 0.05, 0.98, multimask_token_for_ptr=False) == (2, 0)
    assert choose_mask(planes[1:], ious[1:], False, 0.05, 0.98) == (1, 1)  # 3-plane export
    assert choose_mask(planes[:1], ious[:1], True, 0.05, 0.98) == (0, 0)  # baked-in choice


def test_resize_matches_torch_bilinear_half_pixel():
    rng = np.random.default_rng(0)
    x = rng.standard_normal((256, 256)).astype(np.float32)
    for hw in [(1024, 1024), (120, 160), (37, 301)]:
        want = F.interpolate(torch.from_numpy(x)[None, None], size=hw, mode="bilinear",
                             align_corners=False)[0, 0].numpy()
        np.testing.assert_allclose(resize_logits(x, hw), want, atol=1e-4)


def test_scaled_sigmoid_and_bfloat16():
    x = np.linspace(-30, 30, 1001, dtype=np.float32)
    np.testing.assert_allclose(_scaled_sigmoid(x, 20.0, -10.0),
                               20.0 / (1 + np.exp(-x.astype(np.float64))) - 10.0, atol=2e-5)
    np.testing.assert_allclose(_scaled_sigmoid(x, 2.0, 1.0),
                               2.0 / (1 + np.exp(-x.astype(np.float64))) + 1.0, atol=1e-6)
    v = np.random.default_rng(0).standard_normal(10000).astype(np.float32) * 100
    want = torch.from_numpy(v).to(torch.bfloat16).float().numpy()
    np.testing.assert_array_equal(round_bfloat16(v), want)
