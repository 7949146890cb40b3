"""SSIM of 3DGS (Gaussian window), in one module: the evaluation metric
(:func:`cobgs.evaluate.metrics.ssim`) and the training loss (:mod:`cobgs.train.losses`) both
use it."""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F
from torch import Tensor

from cobgs.errors import InputError

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
# Stabilisers of Wang et al. 2004 for a dynamic range of 1: (0.01 L)², (0.03 L)².
SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2


@functools.lru_cache(maxsize=8)
def gauss_1d(size: int, sigma: float, dtype: torch.dtype, device: str) -> Tensor:
    x = torch.arange(size, dtype=torch.float64) - (size // 2)
    g = torch.exp(-(x**2) / (2.0 * sigma**2))
    return (g / g.sum()).to(dtype=dtype, device=device)


def _to_nchw(img: Tensor, name: str) -> Tensor:
    if img.dim() == 3:  # [H, W, C]
        return img.permute(2, 0, 1)[None]
    if img.dim() == 4:  # [B, H, W, C]
        return img.permute(0, 3, 1, 2)
    raise InputError(f"{name} must be [H, W, C] or [B, H, W, C], got {list(img.shape)}")


def _blur(t: Tensor, g: Tensor) -> Tensor:
    """Separable zero-padded Gaussian blur of every channel of [B, K, H, W]."""
    if not (torch.is_grad_enabled() and t.requires_grad):
        from cobgs.render import ops

        if ops.serves(t.device):  # the native op, when the rasterizer already loaded it
            return ops.gauss_blur(t, g)
    k, n = t.shape[1], g.shape[0]
    pad = n // 2
    t = F.conv2d(t, g.view(1, 1, n, 1).expand(k, 1, n, 1), padding=(pad, 0), groups=k)
    return F.conv2d(t, g.view(1, 1, 1, n).expand(k, 1, 1, n), padding=(0, pad), groups=k)


def _ssim_terms(x: Tensor, y: Tensor, g: Tensor):
    c = x.shape[1]
    mu_x, mu_y, exx, eyy, exy = _blur(torch.cat([x, y, x * x, y * y, x * y], 1), g).split(c, 1)
    a1 = 2.0 * mu_x * mu_y + SSIM_C1
    a2 = 2.0 * (exy - mu_x * mu_y) + SSIM_C2
    b1 = mu_x * mu_x + mu_y * mu_y + SSIM_C1
    b2 = (exx - mu_x * mu_x) + (eyy - mu_y * mu_y) + SSIM_C2
    return mu_x, mu_y, a1, a2, b1, b2


def ssim_map(img: Tensor, ref: Tensor, window: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> Tensor:
    """Per-pixel SSIM with a Gaussian window, as in 3DGS (zero padding at the border).

    The 2D window is separable, so the five local statistics (μx, μy, E[x²], E[y²],
    E[xy]) are filtered with two 1D convolutions; this equals 3DGS's 2D convolution.
    Differentiable in both arguments (plain autograd).

    Args:
        img: [H, W, C] or [B, H, W, C].
        ref: same shape as ``img``.

    Returns:
        [B, C, H, W] SSIM values.
    """
    check_pair(img, ref)
    x, y = _to_nchw(img, "img").contiguous(), _to_nchw(ref, "ref").contiguous()
    g = gauss_1d(window, sigma, x.dtype, str(x.device))
    _, _, a1, a2, b1, b2 = _ssim_terms(x, y, g)
    return (a1 * a2) / (b1 * b2)


class _MeanSSIM(torch.autograd.Function):
    """Mean SSIM with a hand-written gradient w.r.t. the first image only.

    With S = A1 A2 / (B1 B2) per window (A1 = 2μxμy + C1, A2 = 2σxy + C2,
    B1 = μx² + μy² + C1, B2 = σx² + σy² + C2) and upstream g = dL/dS:

        ∂S/∂μx    = 2μy (A2 − A1) / (B1 B2) − 2μx S (1/B1 − 1/B2)
        ∂S/∂E[x²] = −S / B2
        ∂S/∂E[xy] = 2 A1 / (B1 B2)
        dL/dx = blur(g ∂S/∂μx) + 2x · blur(g ∂S/∂E[x²]) + y · blur(g ∂S/∂E[xy])

    (the symmetric zero-padded blur is its own adjoint). This needs 3C blurred maps
    instead of autograd's chain of ~40 full-image tensors: the SSIM term was the largest
    cost of a CPU training iteration after the rasterizer.
    """

    @staticmethod
    def forward(ctx, x: Tensor, y: Tensor, g: Tensor) -> Tensor:
        mu_x, mu_y, a1, a2, b1, b2 = _ssim_terms(x, y, g)
        den = b1 * b2
        smap = a1 * a2 / den
        ctx.save_for_backward(x, y, g, mu_x, mu_y, a1, a2, b1, b2)
        return smap.mean()

    @staticmethod
    def backward(ctx, grad_out: Tensor):
        x, y, g, mu_x, mu_y, a1, a2, b1, b2 = ctx.saved_tensors
        scale = grad_out / float(mu_x.numel())
        inv_den = scale / (b1 * b2)
        s_scaled = a1 * a2 * inv_den  # scale · S
        d_mu = 2.0 * mu_y * (a2 - a1) * inv_den - 2.0 * mu_x * s_scaled * (1.0 / b1 - 1.0 / b2)
        d_exx = -s_scaled / b2
        d_exy = 2.0 * a1 * inv_den
        c = x.shape[1]
        b_mu, b_xx, b_xy = _blur(torch.cat([d_mu, d_exx, d_exy], 1), g).split(c, 1)
        return b_mu + 2.0 * x * b_xx + y * b_xy, None, None


class _NativeMeanSSIM(torch.autograd.Function):
    """:class:`_MeanSSIM` on the native ``cobgs::ssim_mean_grad`` op (CPU or CUDA,
    extension loaded): the forward also computes the gradient (one fused pass instead of about 25
    full-image tensors), the backward scales it."""

    @staticmethod
    def forward(ctx, x: Tensor, y: Tensor, g: Tensor) -> Tensor:
        from cobgs.render import ops

        mean, grad = ops.ssim_mean_grad(x.detach(), y.detach(), g)
        ctx.save_for_backward(grad)
        return mean

    @staticmethod
    def backward(ctx, grad_out: Tensor):
        (grad,) = ctx.saved_tensors
        return grad_out * grad, None, None


def check_pair(img: Tensor, ref: Tensor) -> None:
    if img.shape != ref.shape:
        raise InputError(f"img and ref must have the same shape, got {list(img.shape)} and {list(ref.shape)}")


def ssim(img: Tensor, ref: Tensor) -> Tensor:
    """Mean SSIM (scalar) of ``img`` vs ``ref`` ([H, W, C] or [B, H, W, C]).

    When only ``img`` needs a gradient (training against a fixed image) the analytic
    backward of :class:`_MeanSSIM` is used (fused into one native op,
    :class:`_NativeMeanSSIM`, on the CPU and CUDA once the extension is loaded); otherwise plain
    autograd.
    """
    check_pair(img, ref)
    if ref.requires_grad or not img.requires_grad:
        return ssim_map(img, ref).mean()
    x, y = _to_nchw(img, "img").contiguous(), _to_nchw(ref, "ref").contiguous()
    g = gauss_1d(SSIM_WINDOW, SSIM_SIGMA, x.dtype, str(x.device))
    if y.dtype == x.dtype:
        from cobgs.render import ops

        if ops.serves(x.device):  # the native fused op, when the rasterizer already loaded it
            return _NativeMeanSSIM.apply(x, y, g)
    return _MeanSSIM.apply(x, y, g)
