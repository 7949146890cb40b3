"""Photometric losses of 3DGS training: L1 and its mix with SSIM (:mod:`cobgs.evaluate.ssim`)."""

from __future__ import annotations

import torch
from torch import Tensor

from cobgs.errors import InputError
from cobgs.evaluate.ssim import SSIM_SIGMA, SSIM_WINDOW, check_pair, gauss_1d, ssim

def l1_loss(img: Tensor, ref: Tensor) -> Tensor:
    """Mean absolute error (scalar)."""
    if img.shape != ref.shape:
        raise InputError(f"img and ref must have the same shape, got {list(img.shape)} and {list(ref.shape)}")
    return (img - ref).abs().mean()


class _NativePhotometricLoss(torch.autograd.Function):
    """:func:`photometric_loss` on the native ``cobgs::photometric_loss_grad`` op (CPU or
    CUDA, extension loaded, ref fixed): L1, SSIM and the gradient of their mix in one pass over
    the channel-last images (no NCHW copies, no separate L1 graph); the backward scales
    the gradient."""

    @staticmethod
    def forward(ctx, img: Tensor, ref: Tensor, ssim_weight: float) -> Tensor:
        from cobgs.render import ops

        g = gauss_1d(SSIM_WINDOW, SSIM_SIGMA, img.dtype, str(img.device))
        l1, s, grad = ops.photometric_loss_grad(img.detach(), ref.detach(), g, ssim_weight)
        ctx.save_for_backward(grad)
        return (1.0 - ssim_weight) * l1 + ssim_weight * (1.0 - s)

    @staticmethod
    def backward(ctx, grad_out: Tensor):
        (grad,) = ctx.saved_tensors
        return grad_out * grad, None, None


def photometric_loss(img: Tensor, ref: Tensor, ssim_weight: float = 0.2) -> Tensor:
    """3DGS loss: (1 - λ) L1 + λ (1 - SSIM), λ = 0.2.

    With the native extension loaded (CPU, or CUDA when it has its kernels), when only
    ``img`` needs a gradient (a training step), the fused :class:`_NativePhotometricLoss`; otherwise L1 and
    :func:`ssim` separately (same value and gradient up to rounding).

    Args:
        img: [H, W, C] or [B, H, W, C] render.
        ref: the ground truth, same shape.
    """
    check_pair(img, ref)
    if (img.requires_grad and not ref.requires_grad
            and img.dim() in (3, 4) and ref.dtype == img.dtype and ref.device == img.device
            and img.dtype in (torch.float32, torch.float64) and 0.0 <= ssim_weight <= 1.0):
        from cobgs.render import ops

        if ops.serves(img.device):
            return _NativePhotometricLoss.apply(img, ref, float(ssim_weight))
    return (1.0 - ssim_weight) * l1_loss(img, ref) + ssim_weight * (1.0 - ssim(img, ref))
