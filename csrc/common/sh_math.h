// Real spherical harmonics up to degree 3 (3DGS convention), shared by the CPU kernel
// (sh_cpu.cpp) and the CUDA kernel (sh_cuda.cu): the basis, its gradient with respect to
// the direction, and the colour max(Σ_k c_k Y_k(d) + 0.5, 0). Basis order and constants as in
// cobgs/render/sh.py (the pure-PyTorch oracle): coefficient k = l² + l + m.
#pragma once

#include "gs_math.h"

namespace cobgs {
namespace sh {

constexpr int kMaxCoeffs = 16;
constexpr double kC0 = 0.28209479177387814;
constexpr double kC1 = 0.4886025119029199;
// One scalar constant per coefficient (not arrays): CUDA device code may read namespace
// scope constexpr scalars, not arrays.
constexpr double kC2_0 = 1.0925484305920792, kC2_1 = -1.0925484305920792,
                 kC2_2 = 0.31539156525252005, kC2_3 = -1.0925484305920792,
                 kC2_4 = 0.5462742152960396;
constexpr double kC3_0 = -0.5900435899266435, kC3_1 = 2.890611442640554,
                 kC3_2 = -0.4570457994644658, kC3_3 = 0.3731763325901154,
                 kC3_4 = -0.4570457994644658, kC3_5 = 1.445305721320277,
                 kC3_6 = -0.5900435899266435;

// Y[0 .. (degree + 1)²) at the unit direction (x, y, z). T is a lane type (see
// gs_math.h): one direction, or one per lane, bit-identical lane by lane.
template <typename T>
LANE_INLINE void basis(int degree, const T& x, const T& y, const T& z, T* Y) {
  using S = math::LaneS<T>;
  Y[0] = math::splat_lanes<T>(S(kC0));
  if (degree < 1) return;
  Y[1] = -S(kC1) * y;
  Y[2] = S(kC1) * z;
  Y[3] = -S(kC1) * x;
  if (degree < 2) return;
  const T xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  Y[4] = S(kC2_0) * xy;
  Y[5] = S(kC2_1) * yz;
  Y[6] = S(kC2_2) * (S(2) * zz - xx - yy);
  Y[7] = S(kC2_3) * xz;
  Y[8] = S(kC2_4) * (xx - yy);
  if (degree < 3) return;
  Y[9] = S(kC3_0) * y * (S(3) * xx - yy);
  Y[10] = S(kC3_1) * xy * z;
  Y[11] = S(kC3_2) * y * (S(4) * zz - xx - yy);
  Y[12] = S(kC3_3) * z * (S(2) * zz - S(3) * xx - S(3) * yy);
  Y[13] = S(kC3_4) * x * (S(4) * zz - xx - yy);
  Y[14] = S(kC3_5) * z * (xx - yy);
  Y[15] = S(kC3_6) * x * (xx - S(3) * yy);
}

// dL/d(x, y, z) = Σ_k w[k] ∂Y_k/∂(x, y, z) for k in 1 .. (degree + 1)² (Y_0 is constant).
template <typename T>
LANE_INLINE void basis_vjp(int degree, const T& x, const T& y, const T& z, const T* w,
                           T out[3]) {
  using S = math::LaneS<T>;
  T gx{}, gy{}, gz{};
  if (degree >= 1) {
    gy += -S(kC1) * w[1];
    gz += S(kC1) * w[2];
    gx += -S(kC1) * w[3];
  }
  if (degree >= 2) {
    gx += S(kC2_0) * y * w[4];
    gy += S(kC2_0) * x * w[4];
    gy += S(kC2_1) * z * w[5];
    gz += S(kC2_1) * y * w[5];
    gx += S(kC2_2) * S(-2) * x * w[6];
    gy += S(kC2_2) * S(-2) * y * w[6];
    gz += S(kC2_2) * S(4) * z * w[6];
    gx += S(kC2_3) * z * w[7];
    gz += S(kC2_3) * x * w[7];
    gx += S(kC2_4) * S(2) * x * w[8];
    gy += S(kC2_4) * S(-2) * y * w[8];
  }
  if (degree >= 3) {
    const T xx = x * x, yy = y * y, zz = z * z;
    // 9: y (3x² - y²)
    gx += S(kC3_0) * S(6) * x * y * w[9];
    gy += S(kC3_0) * (S(3) * xx - S(3) * yy) * w[9];
    // 10: x y z
    gx += S(kC3_1) * y * z * w[10];
    gy += S(kC3_1) * x * z * w[10];
    gz += S(kC3_1) * x * y * w[10];
    // 11: y (4z² - x² - y²)
    gx += S(kC3_2) * S(-2) * x * y * w[11];
    gy += S(kC3_2) * (S(4) * zz - xx - S(3) * yy) * w[11];
    gz += S(kC3_2) * S(8) * y * z * w[11];
    // 12: z (2z² - 3x² - 3y²)
    gx += S(kC3_3) * S(-6) * x * z * w[12];
    gy += S(kC3_3) * S(-6) * y * z * w[12];
    gz += S(kC3_3) * (S(6) * zz - S(3) * xx - S(3) * yy) * w[12];
    // 13: x (4z² - x² - y²)
    gx += S(kC3_4) * (S(4) * zz - S(3) * xx - yy) * w[13];
    gy += S(kC3_4) * S(-2) * x * y * w[13];
    gz += S(kC3_4) * S(8) * x * z * w[13];
    // 14: z (x² - y²)
    gx += S(kC3_5) * S(2) * x * z * w[14];
    gy += S(kC3_5) * S(-2) * y * z * w[14];
    gz += S(kC3_5) * (xx - yy) * w[14];
    // 15: x (x² - 3y²)
    gx += S(kC3_6) * (S(3) * xx - S(3) * yy) * w[15];
    gy += S(kC3_6) * S(-6) * x * y * w[15];
  }
  out[0] = gx;
  out[1] = gy;
  out[2] = gz;
}


// ---------------------------------------------------------------------------------------
// Per-Gaussian colour and its backward, lane-generic (T: one Gaussian or one per lane).
// C channels, K = (degree + 1)² coefficients; arrays are per-Gaussian values: c0 [C], cn
// [(K - 1) C] (coefficient-major, as in memory), Y [K].

constexpr double kNormMin = 1e-12;  // as GaussianModel.colors: d / max(|d|, 1e-12)

// Unit direction from the camera centre c to the mean m; norm = |m - c| and nc its clamp.
template <typename T>
LANE_INLINE void view_direction(const T m[3], const math::LaneS<T>* c, T dir[3], T& norm,
                                T& nc) {
  using S = math::LaneS<T>;
  const T d0 = m[0] - c[0], d1 = m[1] - c[1], d2 = m[2] - c[2];
  norm = math::lane_sqrt(d0 * d0 + d1 * d1 + d2 * d2);
  nc = math::sel(norm < S(kNormMin), math::splat_lanes<T>(S(kNormMin)), norm);
  dir[0] = d0 / nc;
  dir[1] = d1 / nc;
  dir[2] = d2 / nc;
}

// v[ch] = kC0 c0[ch] + Σ_k Y_k cn[k - 1][ch], summed over k = 1, 2, ... for each channel.
template <typename T>
LANE_INLINE void colour_sum(int C, int K, const T* Y, const T* c0, const T* cn, T* v) {
  using S = math::LaneS<T>;
  for (int ch = 0; ch < C; ++ch) v[ch] = c0[ch] * S(kC0);
  // Coefficients in memory order (k outer); each channel still sums k = 0, 1, ...
  for (int k = 1; k < K; ++k)
    for (int ch = 0; ch < C; ++ch) v[ch] += Y[k] * cn[(k - 1) * C + ch];
}

// The colour max(v + 0.5, 0) (clamp_min; NaN stays NaN).
template <typename T>
LANE_INLINE T clamp_colour(const T& v) {
  using S = math::LaneS<T>;
  const T u = v + S(0.5);
  return math::sel(u < S(0), T{}, u);
}

// Gradients of one Gaussian's colour (C <= 16 channels) given dL/dcolour vcol [C]:
// g0 [C], gn [(K - 1) C] and the mean's gradient through the view direction.
template <typename T>
LANE_INLINE void colour_vjp(int C, int degree, const T* Y, const T dir[3], const T& norm,
                            const T& nc, const T* c0, const T* cn, const T* vcol, T* g0, T* gn,
                            T v_mean[3]) {
  using S = math::LaneS<T>;
  const int K = (degree + 1) * (degree + 1);
  T v[16], g[16];
  colour_sum(C, K, Y, c0, cn, v);
  for (int ch = 0; ch < C; ++ch) {
    // clamp_min's gradient mask (the gradient passes where v + 0.5 >= 0)
    g[ch] = math::sel(v[ch] + S(0.5) >= S(0), vcol[ch], T{});
    g0[ch] = g[ch] * S(kC0);
  }
  T w[kMaxCoeffs];  // Σ_ch c_k[ch] · dL/dv[ch]
  for (int k = 1; k < K; ++k) {
    const T* ck = cn + (k - 1) * C;
    T* gk = gn + (k - 1) * C;
    T wk{};
    for (int ch = 0; ch < C; ++ch) {
      gk[ch] = g[ch] * Y[k];
      wk += ck[ch] * g[ch];
    }
    w[k] = wk;
  }
  if (degree == 0) {
    v_mean[0] = v_mean[1] = v_mean[2] = T{};
    return;
  }
  T vd[3];
  basis_vjp(degree, dir[0], dir[1], dir[2], w, vd);
  // dir = d / max(|d|, eps): project out the radial part (unless the clamp is active).
  const T dot = math::sel(norm >= S(kNormMin), dir[0] * vd[0] + dir[1] * vd[1] + dir[2] * vd[2],
                          T{});
  for (int a = 0; a < 3; ++a) v_mean[a] = (vd[a] - dir[a] * dot) / nc;
}

}  // namespace sh
}  // namespace cobgs
