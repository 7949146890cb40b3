// Op family `gauss_blur`: separable, zero-padded 1D-kernel filtering of image planes, the
// blur of the SSIM loss (cobgs/losses.py `_blur`: a vertical then a horizontal
// cross-correlation with the same odd-length kernel, "same" output size).
#pragma once

#include <torch/types.h>

#include <tuple>

namespace cobgs {

// Args: x [B, K, H, W] float32/float64, g [n] (n odd) of the same dtype.
// Returns [B, K, H, W]: out = corr_x(corr_y(x, g), g) with zero padding n / 2, i.e.
// F.conv2d(F.conv2d(x, g as n x 1, padding (n/2, 0)), g as 1 x n, padding (0, n/2))
// per plane (groups = K).
at::Tensor gauss_blur_cpu(const at::Tensor& x, const at::Tensor& g);

// Mean SSIM of x against y (both [B, C, H, W], dynamic range 1, C1 = 0.01², C2 = 0.03²,
// the separable window g) and its gradient d mean / dx [B, C, H, W] (y held fixed):
// cobgs/losses.py's _MeanSSIM forward and backward in one call (csrc/blur/ssim_cpu.cpp).
std::tuple<at::Tensor, at::Tensor> ssim_mean_grad_cpu(const at::Tensor& x, const at::Tensor& y,
                                                      const at::Tensor& g);

}  // namespace cobgs
