// The per-value SSIM formulas of ssim_mean_grad and photometric_loss_grad, written once
// for the CPU rows (blur_rows_cpu.h: lane vectors of 8 values, or one value) and the CUDA
// kernels (blur_cuda.cu: one value per thread); T is the element type, V a lane type of T
// or T itself (csrc/common/gs_math.h). The formulas and their derivation are in
// ssim_cpu.cpp's header; the operation order is the one both backends round identically.
#pragma once

#include "../common/gs_math.h"

namespace cobgs {
namespace ssim {

template <typename V>
struct Terms {
  V s;              // S = A1 A2 / (B1 B2), the term of the mean
  V d_mu, d_xx, d_xy;  // ∂S/∂μx, ∂S/∂E[x²], ∂S/∂E[xy]
};

// From the five blurred statistics μx, μy, E[x²], E[y²], E[xy] of one value.
template <typename V, typename T>
LANE_INLINE Terms<V> terms(const V& mu_x, const V& mu_y, const V& exx, const V& eyy, const V& exy,
                           T c1, T c2) {
  const V a1 = T(2) * mu_x * mu_y + c1;
  const V a2 = T(2) * (exy - mu_x * mu_y) + c2;
  const V b1 = mu_x * mu_x + mu_y * mu_y + c1;
  const V b2 = (exx - mu_x * mu_x) + (eyy - mu_y * mu_y) + c2;
  const V inv_den = T(1) / (b1 * b2);
  const V smap = a1 * a2 * inv_den;
  Terms<V> t;
  t.s = a1 * a2 / (b1 * b2);
  t.d_mu = T(2) * mu_y * (a2 - a1) * inv_den - T(2) * mu_x * smap * (T(1) / b1 - T(1) / b2);
  t.d_xx = -smap / b2;
  t.d_xy = T(2) * a1 * inv_den;
  return t;
}

// d mean(S) / dx at one value from the blurred partials q (the blur is its own adjoint).
template <typename V, typename T>
LANE_INLINE V grad(const V q[3], const V& x, const V& y, T inv_n) {
  return (q[0] + T(2) * x * q[1] + y * q[2]) * inv_n;
}

// sign(d) with sign(0) = 0, as autograd's gradient of |·|.
template <typename V, typename T>
LANE_INLINE V sign(const V& d) {
  const V zero = math::splat_lanes<V>(T(0)), one = math::splat_lanes<V>(T(1));
  return math::sel(d > zero, one, math::sel(d < zero, -one, zero));
}

template <typename V, typename T>
LANE_INLINE V abs(const V& d) {
  return math::sel(d < math::splat_lanes<V>(T(0)), -d, d);
}

}  // namespace ssim
}  // namespace cobgs
