"""Photometric losses of 3DGS training: L1, SSIM (Gaussian window) and their mix."""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F
from torch import Tensor

from .errors import InputError

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
# Stabilisers of Wang et al. 2004 for a dynamic range of 1: (0.01 L)², (0.03 L)².
SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2


@functools.lru_cache(maxsize=8)
def _gauss_1d(size: int, sigma: float, dtype: torch.dtype, device: str) -> Tensor:
    x = torch.arange(size, dtype=torch.float64) - (size // 2)
    g = torch.exp(-(x**2) / (2.0 * sigma**2))
    return (g / g.sum()).to(dtype=dtype, device=device)


def _to_nchw(img: Tensor, name: str) -> Tensor:
    if img.dim() == 3:  # [H, W, C]
        return img.permute(2, 0, 1)[None]
    if img.dim() == 4:  # [B, H, W, C]
        return img.permute(0, 3, 1, 2)
    raise InputError(f"{name} must be [H, W, C] or [B, H, W, C], got {list(img.shape)}")


def ssim_map(img: Tensor, ref: Tensor, window: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> Tensor:
    """Per-pixel SSIM with a Gaussian window, as in 3DGS (zero padding at the border).

    The 2D window is separable, so the five local statistics (μx, μy, E[x²], E[y²],
    E[xy]) are filtered with two 1D convolutions; this equals 3DGS's 2D convolution.

    Args:
        img: [H, W, C] or [B, H, W, C].
        ref: same shape as ``img``.

    Returns:
        [B, C, H, W] SSIM values.
    """
    if img.shape != ref.shape:
        raise InputError(f"img and ref must have the same shape, got {list(img.shape)} and {list(ref.shape)}")
    x, y = _to_nchw(img, "img"), _to_nchw(ref, "ref")
    b, c, h, w = x.shape
    g = _gauss_1d(window, sigma, x.dtype, str(x.device))
    stats = torch.cat([x, y, x * x, y * y, x * y], 1)  # [B, 5C, H, W]
    k = stats.shape[1]
    pad = window // 2
    stats = F.conv2d(stats, g.view(1, 1, window, 1).expand(k, 1, window, 1), padding=(pad, 0), groups=k)
    stats = F.conv2d(stats, g.view(1, 1, 1, window).expand(k, 1, 1, window), padding=(0, pad), groups=k)
    mu_x, mu_y, exx, eyy, exy = stats.split(c, 1)
    mu_xx, mu_yy, mu_xy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
    var_x, var_y, cov = exx - mu_xx, eyy - mu_yy, exy - mu_xy
    num = (2.0 * mu_xy + SSIM_C1) * (2.0 * cov + SSIM_C2)
    den = (mu_xx + mu_yy + SSIM_C1) * (var_x + var_y + SSIM_C2)
    return num / den


def ssim(img: Tensor, ref: Tensor) -> Tensor:
    """Mean SSIM (scalar) of ``img`` vs ``ref`` ([H, W, C] or [B, H, W, C])."""
    return ssim_map(img, ref).mean()


def l1_loss(img: Tensor, ref: Tensor) -> Tensor:
    """Mean absolute error (scalar)."""
    if img.shape != ref.shape:
        raise InputError(f"img and ref must have the same shape, got {list(img.shape)} and {list(ref.shape)}")
    return (img - ref).abs().mean()


def photometric_loss(img: Tensor, ref: Tensor, ssim_weight: float = 0.2) -> Tensor:
    """3DGS loss: (1 - λ) L1 + λ (1 - SSIM), λ = 0.2.

    Args:
        img: [H, W, C] render.
        ref: [H, W, C] ground truth.
    """
    return (1.0 - ssim_weight) * l1_loss(img, ref) + ssim_weight * (1.0 - ssim(img, ref))
