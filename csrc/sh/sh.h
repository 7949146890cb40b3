// Op family `sh_colors`: view-dependent RGB of 3D Gaussians from their spherical-harmonic
// coefficients, as 3DGS: colour = max(Σ_k c_k Y_k(d) + 0.5, 0), d the unit direction from
// the camera centre to the Gaussian. Formulas: csrc/common/sh_math.h; oracle: cobgs/sh.py
// (sh_to_color) as used by cobgs.gaussians.GaussianModel.colors.
#pragma once

#include <torch/types.h>

#include <tuple>

namespace cobgs {

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

}  // namespace cobgs
