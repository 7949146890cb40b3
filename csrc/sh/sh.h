// Op family `sh_colors`: view-dependent RGB of 3D Gaussians from their spherical-harmonic
// coefficients, as 3DGS: colour = max(Σ_k c_k Y_k(d) + 0.5, 0), d the unit direction from
// the camera centre to the Gaussian. Formulas: csrc/common/sh_math.h; oracle: cobgs/render/sh.py
// (sh_to_color) as used by cobgs.train.gaussians.GaussianModel.colors.
#pragma once

#include <torch/types.h>

#include <tuple>

#include "../common/checks.h"

namespace cobgs {

constexpr int kMaxShChannels = 16;  // per-Gaussian channel values live in registers

// Shape, dtype and device checks of sh_colors / sh_colors_bwd (shared by both backends;
// the caller has checked the device type of means).
inline void check_sh_inputs(const at::Tensor& means, const at::Tensor& sh0,
                            const at::Tensor& shN, const at::Tensor& center, int64_t degree) {
  COBGS_CHECK_CONTIGUOUS(means);
  COBGS_CHECK_LIKE(sh0, means);
  COBGS_CHECK_LIKE(shN, means);
  COBGS_CHECK_LIKE(center, means);
  TORCH_CHECK(means.scalar_type() == at::kFloat || means.scalar_type() == at::kDouble,
              "means must be float32 or float64, got ", means.scalar_type());
  TORCH_CHECK(means.dim() == 2, "means must have shape [N, 3], got ", means.sizes());
  TORCH_CHECK(sh0.dim() == 3, "sh0 must have shape [N, 1, C], got ", sh0.sizes());
  const int64_t n = means.size(0), c = sh0.size(2);
  TORCH_CHECK(c >= 1 && c <= kMaxShChannels, "sh0 must have 1..", kMaxShChannels,
              " channels, got ", sh0.sizes());
  COBGS_CHECK_SHAPE(means, n, 3);
  COBGS_CHECK_SHAPE(sh0, n, 1, c);
  COBGS_CHECK_SHAPE(shN, n, -1, c);
  COBGS_CHECK_SHAPE(center, 3);
  for (const auto* t : {&sh0, &shN, &center}) COBGS_CHECK_DTYPE((*t), means.scalar_type());
  TORCH_CHECK(degree >= 0 && degree <= 3, "degree must be in 0..3, got ", degree);
  TORCH_CHECK(shN.size(1) >= (degree + 1) * (degree + 1) - 1, "shN must have at least ",
              (degree + 1) * (degree + 1) - 1, " coefficients for degree ", degree, ", got ",
              shN.sizes());
}

inline void check_sh_bwd_input(const at::Tensor& means, const at::Tensor& sh0,
                               const at::Tensor& v_colors) {
  COBGS_CHECK_LIKE(v_colors, means);
  COBGS_CHECK_DTYPE(v_colors, means.scalar_type());
  COBGS_CHECK_SHAPE(v_colors, means.size(0), sh0.size(2));
}

// Args:
//   means [N, 3] world positions       sh0 [N, 1, C] DC coefficients
//   shN [N, M, C] higher coefficients (M >= (degree + 1)² - 1; the rest is ignored)
//   center [3] camera centre           degree: active SH degree 0..3
// Returns colors [N, C].
at::Tensor sh_colors_cpu(const at::Tensor& means, const at::Tensor& sh0, const at::Tensor& shN,
                         const at::Tensor& center, int64_t degree);

// Backward of sh_colors_cpu for the incoming gradient v_colors [N, C].
// Returns v_means [N, 3] (through the direction; zero for degree 0), v_sh0 [N, 1, C],
// v_shN [N, M, C] (zero beyond the active degree).
std::tuple<at::Tensor, at::Tensor, at::Tensor> sh_colors_bwd_cpu(
    const at::Tensor& means, const at::Tensor& sh0, const at::Tensor& shN,
    const at::Tensor& center, int64_t degree, const at::Tensor& v_colors);

// The CUDA implementations (csrc/sh/sh_cuda.cu; builds with CUDA only).
at::Tensor sh_colors_cuda(const at::Tensor& means, const at::Tensor& sh0, const at::Tensor& shN,
                          const at::Tensor& center, int64_t degree);
std::tuple<at::Tensor, at::Tensor, at::Tensor> sh_colors_bwd_cuda(
    const at::Tensor& means, const at::Tensor& sh0, const at::Tensor& shN,
    const at::Tensor& center, int64_t degree, const at::Tensor& v_colors);

}  // namespace cobgs
