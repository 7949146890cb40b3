// Op family `gauss_blur`: separable, zero-padded 1D-kernel filtering of image planes, the
// blur of the SSIM loss (cobgs/train/losses.py `_blur`: a vertical then a horizontal
// cross-correlation with the same odd-length kernel, "same" output size).
#pragma once

#include <torch/types.h>

#include <tuple>

#include "../common/checks.h"

namespace cobgs {

// Input checks of the three ops, shared by both backends (the caller has checked the
// device type of the first tensor).
inline void check_blur_inputs(const at::Tensor& x, const at::Tensor& g) {
  COBGS_CHECK_CONTIGUOUS(x);
  COBGS_CHECK_LIKE(g, x);
  TORCH_CHECK(x.scalar_type() == at::kFloat || x.scalar_type() == at::kDouble,
              "x must be float32 or float64, got ", x.scalar_type());
  TORCH_CHECK(x.dim() == 4, "x must have shape [B, K, H, W], got ", x.sizes());
  TORCH_CHECK(g.dim() == 1 && g.size(0) % 2 == 1, "g must be 1-D with an odd length, got ",
              g.sizes());
  COBGS_CHECK_DTYPE(g, x.scalar_type());
}

inline void check_ssim_inputs(const at::Tensor& x, const at::Tensor& y, const at::Tensor& g) {
  COBGS_CHECK_CONTIGUOUS(x);
  COBGS_CHECK_LIKE(y, x);
  COBGS_CHECK_LIKE(g, x);
  TORCH_CHECK(x.scalar_type() == at::kFloat || x.scalar_type() == at::kDouble,
              "x must be float32 or float64, got ", x.scalar_type());
  TORCH_CHECK(x.dim() == 4, "x must have shape [B, C, H, W], got ", x.sizes());
  TORCH_CHECK(y.sizes() == x.sizes(), "y must have the shape of x ", x.sizes(), ", got ",
              y.sizes());
  TORCH_CHECK(g.dim() == 1 && g.size(0) % 2 == 1, "g must be 1-D with an odd length, got ",
              g.sizes());
  COBGS_CHECK_DTYPE(y, x.scalar_type());
  COBGS_CHECK_DTYPE(g, x.scalar_type());
  TORCH_CHECK(x.numel() > 0, "x must not be empty");
}

inline void check_photometric_inputs(const at::Tensor& img, const at::Tensor& ref,
                                     const at::Tensor& g, double ssim_weight) {
  COBGS_CHECK_CONTIGUOUS(img);
  COBGS_CHECK_LIKE(ref, img);
  COBGS_CHECK_LIKE(g, img);
  TORCH_CHECK(img.scalar_type() == at::kFloat || img.scalar_type() == at::kDouble,
              "img must be float32 or float64, got ", img.scalar_type());
  TORCH_CHECK(img.dim() == 3 || img.dim() == 4,
              "img must have shape [H, W, C] or [B, H, W, C], got ", img.sizes());
  TORCH_CHECK(ref.sizes() == img.sizes(), "ref must have the shape of img ", img.sizes(),
              ", got ", ref.sizes());
  TORCH_CHECK(g.dim() == 1 && g.size(0) % 2 == 1, "g must be 1-D with an odd length, got ",
              g.sizes());
  COBGS_CHECK_DTYPE(ref, img.scalar_type());
  COBGS_CHECK_DTYPE(g, img.scalar_type());
  TORCH_CHECK(img.numel() > 0, "img must not be empty");
  TORCH_CHECK(ssim_weight >= 0.0 && ssim_weight <= 1.0, "ssim_weight must be in [0, 1], got ",
              ssim_weight);
}

// Args: x [B, K, H, W] float32/float64, g [n] (n odd) of the same dtype.
// Returns [B, K, H, W]: out = corr_x(corr_y(x, g), g) with zero padding n / 2, i.e.
// F.conv2d(F.conv2d(x, g as n x 1, padding (n/2, 0)), g as 1 x n, padding (0, n/2))
// per plane (groups = K).
at::Tensor gauss_blur_cpu(const at::Tensor& x, const at::Tensor& g);

// Mean SSIM of x against y (both [B, C, H, W], dynamic range 1, C1 = 0.01², C2 = 0.03²,
// the separable window g) and its gradient d mean / dx [B, C, H, W] (y held fixed):
// cobgs/train/losses.py's _MeanSSIM forward and backward in one call (csrc/blur/ssim_cpu.cpp).
std::tuple<at::Tensor, at::Tensor> ssim_mean_grad_cpu(const at::Tensor& x, const at::Tensor& y,
                                                      const at::Tensor& g);

// SSIM's stabilising constants for a dynamic range of 1.
constexpr double kSsimC1 = 0.01 * 0.01;
constexpr double kSsimC2 = 0.03 * 0.03;

namespace blur_detail {
// ssim_mean_grad on raw planes (csrc/blur/blur_rows_cpu.h, ssim_planes): x, y, grad and
// the scratch `parts` (3 x planes x H x W) hold `planes` planes of H x W each. Writes the
// gradient of the mean SSIM into grad and returns the sum of the SSIM map.
template <typename T>
double ssim_mean_grad_planes(const T* x, const T* y, int64_t planes, int H, int W, const T* g,
                             int n, T* parts, T* grad);
// The photometric loss's gradient on channel-interleaved images [batch, H, W, C]:
// grad = w_l1·sign(x − y) + w_ssim·d mean(S)/dx; returns Σ S, and Σ |x − y| in *l1_sum.
// `parts` is scratch for 3 x batch x H x W x C values.
template <typename T>
double photometric_grad_rows(const T* x, const T* y, int64_t batch, int H, int W, int C,
                             const T* g, int n, T* parts, T* grad, double w_l1, double w_ssim,
                             double* l1_sum);
}  // namespace blur_detail

// The 3DGS photometric loss L = (1 − λ)·mean|img − ref| + λ·(1 − mean SSIM(img, ref)) of
// channel-last images img, ref [H, W, C] or [B, H, W, C] (SSIM per channel with the window
// g, as ssim_mean_grad) and dL/dimg, without reordering the images: returns (mean L1,
// mean SSIM, dL/dimg). λ = ssim_weight in [0, 1].
std::tuple<at::Tensor, at::Tensor, at::Tensor> photometric_loss_grad_cpu(const at::Tensor& img,
                                                                        const at::Tensor& ref,
                                                                        const at::Tensor& g,
                                                                        double ssim_weight);

// The CUDA implementations (csrc/blur/blur_cuda.cu; builds with CUDA only).
at::Tensor gauss_blur_cuda(const at::Tensor& x, const at::Tensor& g);
std::tuple<at::Tensor, at::Tensor> ssim_mean_grad_cuda(const at::Tensor& x, const at::Tensor& y,
                                                       const at::Tensor& g);
std::tuple<at::Tensor, at::Tensor, at::Tensor> photometric_loss_grad_cuda(const at::Tensor& img,
                                                                         const at::Tensor& ref,
                                                                         const at::Tensor& g,
                                                                         double ssim_weight);

}  // namespace cobgs
