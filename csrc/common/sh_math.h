// Real spherical harmonics up to degree 3 (3DGS convention), shared by the CPU kernel
// (sh_cpu.cpp) and, later, CUDA: the basis, its gradient with respect to the direction,
// and the colour max(Σ_k c_k Y_k(d) + 0.5, 0). Basis order and constants as in
// cobgs/sh.py (the pure-PyTorch oracle): coefficient k = l² + l + m.
#pragma once

#include "gs_math.h"

namespace cobgs {
namespace sh {

constexpr int kMaxCoeffs = 16;
constexpr double kC0 = 0.28209479177387814;
constexpr double kC1 = 0.4886025119029199;
constexpr double kC2[5] = {1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
                           -1.0925484305920792, 0.5462742152960396};
constexpr double kC3[7] = {-0.5900435899266435, 2.890611442640554, -0.4570457994644658,
                           0.3731763325901154,  -0.4570457994644658, 1.445305721320277,
                           -0.5900435899266435};

// Y[0 .. (degree + 1)²) at the unit direction (x, y, z).
template <typename T>
HOST_DEVICE inline void basis(int degree, T x, T y, T z, T* Y) {
  Y[0] = T(kC0);
  if (degree < 1) return;
  Y[1] = -T(kC1) * y;
  Y[2] = T(kC1) * z;
  Y[3] = -T(kC1) * x;
  if (degree < 2) return;
  const T xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  Y[4] = T(kC2[0]) * xy;
  Y[5] = T(kC2[1]) * yz;
  Y[6] = T(kC2[2]) * (T(2) * zz - xx - yy);
  Y[7] = T(kC2[3]) * xz;
  Y[8] = T(kC2[4]) * (xx - yy);
  if (degree < 3) return;
  Y[9] = T(kC3[0]) * y * (T(3) * xx - yy);
  Y[10] = T(kC3[1]) * xy * z;
  Y[11] = T(kC3[2]) * y * (T(4) * zz - xx - yy);
  Y[12] = T(kC3[3]) * z * (T(2) * zz - T(3) * xx - T(3) * yy);
  Y[13] = T(kC3[4]) * x * (T(4) * zz - xx - yy);
  Y[14] = T(kC3[5]) * z * (xx - yy);
  Y[15] = T(kC3[6]) * x * (xx - T(3) * yy);
}

// dL/d(x, y, z) = Σ_k w[k] ∂Y_k/∂(x, y, z) for k in 1 .. (degree + 1)² (Y_0 is constant).
template <typename T>
HOST_DEVICE inline void basis_vjp(int degree, T x, T y, T z, const T* w, T out[3]) {
  T gx = T(0), gy = T(0), gz = T(0);
  if (degree >= 1) {
    gy += -T(kC1) * w[1];
    gz += T(kC1) * w[2];
    gx += -T(kC1) * w[3];
  }
  if (degree >= 2) {
    gx += T(kC2[0]) * y * w[4];
    gy += T(kC2[0]) * x * w[4];
    gy += T(kC2[1]) * z * w[5];
    gz += T(kC2[1]) * y * w[5];
    gx += T(kC2[2]) * T(-2) * x * w[6];
    gy += T(kC2[2]) * T(-2) * y * w[6];
    gz += T(kC2[2]) * T(4) * z * w[6];
    gx += T(kC2[3]) * z * w[7];
    gz += T(kC2[3]) * x * w[7];
    gx += T(kC2[4]) * T(2) * x * w[8];
    gy += T(kC2[4]) * T(-2) * y * w[8];
  }
  if (degree >= 3) {
    const T xx = x * x, yy = y * y, zz = z * z;
    // 9: y (3x² - y²)
    gx += T(kC3[0]) * T(6) * x * y * w[9];
    gy += T(kC3[0]) * (T(3) * xx - T(3) * yy) * w[9];
    // 10: x y z
    gx += T(kC3[1]) * y * z * w[10];
    gy += T(kC3[1]) * x * z * w[10];
    gz += T(kC3[1]) * x * y * w[10];
    // 11: y (4z² - x² - y²)
    gx += T(kC3[2]) * T(-2) * x * y * w[11];
    gy += T(kC3[2]) * (T(4) * zz - xx - T(3) * yy) * w[11];
    gz += T(kC3[2]) * T(8) * y * z * w[11];
    // 12: z (2z² - 3x² - 3y²)
    gx += T(kC3[3]) * T(-6) * x * z * w[12];
    gy += T(kC3[3]) * T(-6) * y * z * w[12];
    gz += T(kC3[3]) * (T(6) * zz - T(3) * xx - T(3) * yy) * w[12];
    // 13: x (4z² - x² - y²)
    gx += T(kC3[4]) * (T(4) * zz - T(3) * xx - yy) * w[13];
    gy += T(kC3[4]) * T(-2) * x * y * w[13];
    gz += T(kC3[4]) * T(8) * x * z * w[13];
    // 14: z (x² - y²)
    gx += T(kC3[5]) * T(2) * x * z * w[14];
    gy += T(kC3[5]) * T(-2) * y * z * w[14];
    gz += T(kC3[5]) * (xx - yy) * w[14];
    // 15: x (x² - 3y²)
    gx += T(kC3[6]) * (T(3) * xx - T(3) * yy) * w[15];
    gy += T(kC3[6]) * T(-6) * x * y * w[15];
  }
  out[0] = gx;
  out[1] = gy;
  out[2] = gz;
}

}  // namespace sh
}  // namespace cobgs
