"""Metrics: PSNR, SSIM (against a direct 2D-window implementation), IoU, accuracy, BIoU."""

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from cobgs.evaluate import metrics
from cobgs.errors import InputError
from cobgs.evaluate.ssim import ssim
from cobgs.train.losses import photometric_loss


def _ssim_2d(x, y):
    """3DGS's formulation: one 11x11 Gaussian 2D convolution, zero padding 5."""
    g = torch.exp(-((torch.arange(11, dtype=torch.float64) - 5) ** 2) / (2 * 1.5**2))
    g = g / g.sum()
    w = (g[:, None] @ g[None, :]).expand(3, 1, 11, 11)
    x, y = x.permute(2, 0, 1)[None].double(), y.permute(2, 0, 1)[None].double()
    f = lambda t: F.conv2d(t, w, padding=5, groups=3)
    mx, my = f(x), f(y)
    sxx, syy, sxy = f(x * x) - mx**2, f(y * y) - my**2, f(x * y) - mx * my
    c1, c2 = 0.01**2, 0.03**2
    return (((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx**2 + my**2 + c1) * (sxx + syy + c2))).mean()


def test_ssim_matches_2d_window_and_skimage_interior():
    g = torch.Generator().manual_seed(0)
    a = torch.rand(40, 52, 3, generator=g)
    b = (a + 0.1 * torch.randn(40, 52, 3, generator=g)).clamp(0, 1)
    assert float(ssim(a, b)) == pytest.approx(float(_ssim_2d(a, b)), abs=1e-6)
    assert float(ssim(a, a)) == pytest.approx(1.0, abs=1e-6)
    assert metrics.ssim(a, b) == pytest.approx(float(_ssim_2d(a, b)), abs=1e-6)
    loss = photometric_loss(a, b)
    assert float(loss) == pytest.approx(0.8 * float((a - b).abs().mean()) + 0.2 * (1 - float(_ssim_2d(a, b))), abs=1e-6)


def test_psnr_known_value():
    a = torch.zeros(10, 10, 3)
    b = torch.full((10, 10, 3), 0.1)
    assert metrics.psnr(a, b) == pytest.approx(20.0)
    assert metrics.psnr(a, a) == math.inf
    with pytest.raises(InputError, match="shape"):
        metrics.psnr(a, torch.zeros(10, 9, 3))


def test_iou_accuracy_hand_case():
    gt = np.zeros((4, 5), bool)
    gt[1:3, 1:4] = True  # 6 pixels
    pred = np.zeros((4, 5), bool)
    pred[1:3, 2:5] = True  # 6 pixels, overlap 4
    assert metrics.iou(pred, gt) == pytest.approx(4 / 8)
    assert metrics.accuracy(pred, gt) == pytest.approx(16 / 20)
    assert metrics.iou(torch.from_numpy(pred), torch.from_numpy(gt)) == pytest.approx(0.5)
    empty = np.zeros((4, 5), bool)
    assert metrics.iou(empty, empty) == 1.0
    with pytest.raises(InputError, match="boolean"):
        metrics.iou(pred.astype(np.uint8), gt)
    assert np.array_equal(metrics.binarize(np.array([[0, 128, 129, 255]])), [[False, False, True, True]])


def test_boundary_band_and_biou():
    # 100x100 image: diagonal 141.4 → d = round(2.83) = 3 erosion iterations.
    assert metrics.boundary_width(100, 100) == 3
    m = np.zeros((100, 100), bool)
    m[20:60, 30:80] = True  # 40 x 50
    band = metrics.mask_boundary(m)
    # Inner band of width 3: 40*50 - 34*44 pixels.
    assert band.sum() == 40 * 50 - 34 * 44
    assert not band[25:55, 35:75].any() and band[20, 30] and band[22, 50]
    # A mask touching the border: the zero pad makes border pixels boundary too.
    full = np.ones((100, 100), bool)
    assert metrics.mask_boundary(full).sum() == 100 * 100 - 94 * 94
    assert metrics.boundary_iou(m, m) == 1.0
    shifted = np.roll(m, 1, axis=1)
    b1, b2 = metrics.mask_boundary(m), metrics.mask_boundary(shifted)
    expect = (b1 & b2).sum() / (b1 | b2).sum()
    assert metrics.boundary_iou(shifted, m) == pytest.approx(expect)
    assert metrics.boundary_iou(shifted, m) < metrics.iou(shifted, m)  # boundary is stricter


def test_ssim_analytic_gradient():
    g = torch.Generator().manual_seed(1)
    x = torch.rand(13, 17, 3, generator=g, dtype=torch.float64, requires_grad=True)
    y = torch.rand(13, 17, 3, generator=g, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda t: ssim(t, y), (x,))
    # Same gradient as autograd through the 2D-window formulation.
    (ga,) = torch.autograd.grad(ssim(x, y), x)
    (gb,) = torch.autograd.grad(_ssim_2d(x, y), x)
    assert torch.allclose(ga, gb, rtol=1e-9, atol=1e-12)
