// One Gaussian of the `sh_colors` op family, shared by the CPU loops (sh_lanes_cpu.h,
// which also run 8 Gaussians at a time in the training case) and the CUDA kernels
// (sh_cuda.cu, one thread per Gaussian): the arguments, and the forward and backward of
// Gaussian i through the formulas of csrc/common/sh_math.h.
#pragma once

#include <cstdint>

#include "../common/sh_math.h"
#include "sh.h"

namespace cobgs {

template <typename T>
struct ShArgs {
  const T* means;   // [N, 3]
  const T* sh0;     // [N, 1, C]
  const T* shN;     // [N, M, C]
  const T* center;  // [3]
  int64_t M;
  int C, degree;
  T* out;  // [N, C]
};

template <typename T>
struct ShBwdArgs {
  const T* means;
  const T* sh0;
  const T* shN;
  const T* center;
  int64_t M;
  int C, degree;
  const T* v_col;  // [N, C]
  T* v_means;      // [N, 3]     (every output element is written)
  T* v_sh0;        // [N, 1, C]
  T* v_shN;        // [N, M, C]
};

template <typename T, int CC, int DEG>
HOST_DEVICE inline void sh_forward_one(const ShArgs<T>& a, int64_t i) {
  const int C = CC > 0 ? CC : a.C;
  const int degree = DEG >= 0 ? DEG : a.degree;
  const int K = (degree + 1) * (degree + 1);
  T Y[sh::kMaxCoeffs];
  if (degree > 0) {
    T dir[3], norm, nc;
    sh::view_direction(a.means + 3 * i, a.center, dir, norm, nc);
    sh::basis(degree, dir[0], dir[1], dir[2], Y);
  }
  T v[kMaxShChannels];
  sh::colour_sum(C, K, Y, a.sh0 + i * C, a.shN + i * a.M * C, v);
  for (int ch = 0; ch < C; ++ch) a.out[i * C + ch] = sh::clamp_colour(v[ch]);
}

template <typename T, int CC, int DEG>
HOST_DEVICE inline void sh_backward_one(const ShBwdArgs<T>& a, int64_t i) {
  const int C = CC > 0 ? CC : a.C;
  const int degree = DEG >= 0 ? DEG : a.degree;
  const int K = (degree + 1) * (degree + 1);
  T* g0 = a.v_sh0 + i * C;
  T* gn = a.v_shN + i * a.M * C;
  T* vm = a.v_means + 3 * i;
  const T* vcol = a.v_col + i * C;
  bool any_grad = false;
  for (int ch = 0; ch < C; ++ch) any_grad |= vcol[ch] != T(0);
  if (!any_grad) {  // e.g. a Gaussian hidden in this view: every gradient is zero
    for (int ch = 0; ch < C; ++ch) g0[ch] = T(0);
    for (int64_t k = 0; k < a.M * C; ++k) gn[k] = T(0);
    vm[0] = vm[1] = vm[2] = T(0);
    return;
  }
  T Y[sh::kMaxCoeffs], dir[3], norm = T(0), nc = T(1);
  if (degree > 0) {
    sh::view_direction(a.means + 3 * i, a.center, dir, norm, nc);
    sh::basis(degree, dir[0], dir[1], dir[2], Y);
  }
  sh::colour_vjp(C, degree, Y, dir, norm, nc, a.sh0 + i * C, a.shN + i * a.M * C, vcol, g0, gn,
                 vm);
  for (int64_t k = (K - 1) * C; k < a.M * C; ++k) gn[k] = T(0);
}

}  // namespace cobgs
