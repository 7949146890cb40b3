// Op family `gauss_blur`: separable, zero-padded 1D-kernel filtering of image planes, the
// blur of the SSIM loss (cobgs/losses.py `_blur`: a vertical then a horizontal
// cross-correlation with the same odd-length kernel, "same" output size).
#pragma once

#include <torch/types.h>

namespace cobgs {

// Args: x [B, K, H, W] float32/float64, g [n] (n odd) of the same dtype.
// Returns [B, K, H, W]: out = corr_x(corr_y(x, g), g) with zero padding n / 2, i.e.
// F.conv2d(F.conv2d(x, g as n x 1, padding (n/2, 0)), g as 1 x n, padding (0, n/2))
// per plane (groups = K).
at::Tensor gauss_blur_cpu(const at::Tensor& x, const at::Tensor& g);

}  // namespace cobgs
