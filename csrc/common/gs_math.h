// Device-agnostic math of the Gaussian rasterizer: one definition of every formula,
// shared by the CPU kernels (*_cpu.cpp) and, later, CUDA kernels (*_cuda.cu). Only plain
// scalars, lane vectors and fixed-size structs; no ATen, no allocation, no OpenMP.
//
// The projection formulas are templates over a *lane type* T: a scalar (float or double)
// or, on the CPU, a GCC/Clang vector of floats, so that one definition evaluates one
// Gaussian or 8 at once (csrc/project/project_lanes_cpu.h). Lane code uses only exactly
// rounded IEEE operations (+ - * /, sqrt, ceil, comparisons, selects) and no branches on
// values, so every lane of a vector evaluation is bit-identical to the scalar one.
//
// The contract these formulas implement is written out in cobgs/render/reference.py (the
// pure-PyTorch oracle); keep the two in step. Expressions that decide whether a
// (Gaussian, pixel) pair contributes (`pixel_power`, `pixel_alpha`) are written with the
// same operation order as the reference, and the extension is compiled with
// -ffp-contract=off, so float decisions agree bit for bit between forward and backward.
#pragma once

#include <cmath>
#include <cstdint>
#include <cstring>
#include <type_traits>
#include <utility>

#if defined(__CUDACC__) || defined(__HIPCC__)
#define HOST_DEVICE __host__ __device__
#define LANE_INLINE __host__ __device__ __forceinline__
#elif defined(__GNUC__) || defined(__clang__)
#define HOST_DEVICE
// Lane functions are always inlined, so that a caller compiled for AVX2 / AVX-512 (see
// csrc/common/simd_cpu.h) gets them in its own instruction set.
#define LANE_INLINE __attribute__((always_inline)) inline
#else
#define HOST_DEVICE
#define LANE_INLINE inline
#endif

namespace cobgs {
namespace math {

constexpr int kTileSize = 16;
constexpr int kTilePixels = kTileSize * kTileSize;
constexpr double kLowpass = 0.3;        // px², added to the 2D covariance diagonal (EWA)
constexpr double kFrustumSlack = 0.3;   // Jacobian clamp: FoV widened by 0.3 tan(FoV/2)
constexpr double kAlphaMin = 1.0 / 255.0;
constexpr double kAlphaMax = 0.99;
constexpr double kTransmittanceMin = 1e-4;
constexpr double kMinEigenGap = 0.1;    // 3DGS: λmax = mid + sqrt(max(0.1, mid² - det))
constexpr double kMaxRadius = 1073741824.0;  // 2^30: keeps radii representable in int32

// ---------------------------------------------------------------------------------------
// Lane types: S is the element type, Mask the type of a comparison (bool for scalars, an
// integer vector of -1 / 0 for vectors). Masks combine with & and |, never && / ||.
template <typename T, typename = void>
struct LaneTraits {
  using S = T;
  using Mask = bool;
  static constexpr bool kVector = false;
};
#if !defined(__CUDACC__) && !defined(__HIPCC__)
template <typename T>
struct LaneTraits<T, std::void_t<decltype(std::declval<T&>()[0])>> {
  using S = std::decay_t<decltype(std::declval<T&>()[0])>;
  using Mask = decltype(std::declval<T>() < std::declval<T>());
  static constexpr bool kVector = true;
  static constexpr int kWidth = sizeof(T) / sizeof(S);
};
#endif
template <typename T>
using LaneS = typename LaneTraits<T>::S;
template <typename T>
using LaneMask = typename LaneTraits<T>::Mask;

// m ? a : b, lane-wise for vectors.
template <typename M, typename T>
LANE_INLINE T sel(const M& m, const T& a, const T& b) {
  return m ? a : b;
}

template <typename T>
LANE_INLINE T splat_lanes(LaneS<T> s) {
  if constexpr (LaneTraits<T>::kVector) {
    T r;
    for (int k = 0; k < LaneTraits<T>::kWidth; ++k) r[k] = s;
    return r;
  } else {
    return s;
  }
}

template <typename M>
LANE_INLINE M lane_not(const M& m) {
  if constexpr (std::is_same_v<M, bool>) {
    return !m;
  } else {
    return ~m;
  }
}

// True when some lane is set.
template <typename M>
LANE_INLINE bool lane_any(const M& m) {
  if constexpr (std::is_same_v<M, bool>) {
    return m;
  } else {
    bool r = false;
    for (size_t k = 0; k < sizeof(M) / sizeof(m[0]); ++k) r |= m[k] != 0;
    return r;
  }
}

// f applied lane by lane (the compiler turns the loop into vector instructions where the
// instruction set has them), or to the scalar. The functions below are exactly rounded.
template <typename T, typename F>
LANE_INLINE T lane_map(const T& x, F f) {
  if constexpr (LaneTraits<T>::kVector) {
    T r;
    for (int k = 0; k < LaneTraits<T>::kWidth; ++k) r[k] = f(x[k]);
    return r;
  } else {
    return f(x);
  }
}

struct SqrtFn {
  template <typename S>
  LANE_INLINE S operator()(S v) const { return std::sqrt(v); }
};
struct CeilFn {
  template <typename S>
  LANE_INLINE S operator()(S v) const { return std::ceil(v); }
};
struct FloorFn {
  template <typename S>
  LANE_INLINE S operator()(S v) const { return std::floor(v); }
};

template <typename T>
LANE_INLINE T lane_sqrt(const T& x) { return lane_map(x, SqrtFn{}); }
template <typename T>
LANE_INLINE T lane_ceil(const T& x) { return lane_map(x, CeilFn{}); }
template <typename T>
LANE_INLINE T lane_floor(const T& x) { return lane_map(x, FloorFn{}); }

// Neither infinite nor NaN (x - x is 0 exactly for every finite x, NaN otherwise).
template <typename T>
LANE_INLINE LaneMask<T> lane_isfinite(const T& x) {
  if constexpr (LaneTraits<T>::kVector) {
    return (x - x) == LaneS<T>(0);
  } else {
    return std::isfinite(x);
  }
}

// ---------------------------------------------------------------------------------------
// Projection.

template <typename T>
struct Vec3 {
  T x, y, z;
};

// Row-major 3x3 matrix.
template <typename T>
struct Mat3 {
  T m[3][3];
};

template <typename T>
LANE_INLINE Mat3<T> transpose(const Mat3<T>& a) {
  Mat3<T> r;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) r.m[i][j] = a.m[j][i];
  return r;
}

// A (scalar or lanes) times B (lanes): the product's lane type is B's.
template <typename A, typename B>
LANE_INLINE Mat3<B> matmul(const Mat3<A>& a, const Mat3<B>& b) {
  Mat3<B> r;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) {
      B s{};
      for (int k = 0; k < 3; ++k) s += a.m[i][k] * b.m[k][j];
      r.m[i][j] = s;
    }
  return r;
}

template <typename A, typename B>
LANE_INLINE Vec3<B> matvec(const Mat3<A>& a, const Vec3<B>& v) {
  return {a.m[0][0] * v.x + a.m[0][1] * v.y + a.m[0][2] * v.z,
          a.m[1][0] * v.x + a.m[1][1] * v.y + a.m[1][2] * v.z,
          a.m[2][0] * v.x + a.m[2][1] * v.y + a.m[2][2] * v.z};
}

// Rotation matrix of a unit quaternion (w, x, y, z).
template <typename T>
LANE_INLINE Mat3<T> quat_to_rotmat(const T& w, const T& x, const T& y, const T& z) {
  using S = LaneS<T>;
  Mat3<T> r;
  r.m[0][0] = S(1) - S(2) * (y * y + z * z);
  r.m[0][1] = S(2) * (x * y - w * z);
  r.m[0][2] = S(2) * (x * z + w * y);
  r.m[1][0] = S(2) * (x * y + w * z);
  r.m[1][1] = S(1) - S(2) * (x * x + z * z);
  r.m[1][2] = S(2) * (y * z - w * x);
  r.m[2][0] = S(2) * (x * z - w * y);
  r.m[2][1] = S(2) * (y * z + w * x);
  r.m[2][2] = S(1) - S(2) * (x * x + y * y);
  return r;
}

// Vector-Jacobian product of quat_to_rotmat: dL/d(w, x, y, z) from dL/dR.
template <typename T>
LANE_INLINE void quat_to_rotmat_vjp(const T& w, const T& x, const T& y, const T& z,
                                    const Mat3<T>& v, T out[4]) {
  using S = LaneS<T>;
  const T(*g)[3] = v.m;
  out[0] = S(2) * (-z * g[0][1] + y * g[0][2] + z * g[1][0] - x * g[1][2] - y * g[2][0] +
                   x * g[2][1]);
  out[1] = S(2) * (y * g[0][1] + z * g[0][2] + y * g[1][0] - S(2) * x * g[1][1] -
                   w * g[1][2] + z * g[2][0] + w * g[2][1] - S(2) * x * g[2][2]);
  out[2] = S(2) * (-S(2) * y * g[0][0] + x * g[0][1] + w * g[0][2] + x * g[1][0] +
                   z * g[1][2] - w * g[2][0] + z * g[2][1] - S(2) * y * g[2][2]);
  out[3] = S(2) * (-S(2) * z * g[0][0] - w * g[0][1] + x * g[0][2] + w * g[1][0] -
                   S(2) * z * g[1][1] + y * g[1][2] + x * g[2][0] + y * g[2][1]);
}

// Camera of one view: rotation/translation of the world->camera transform and the
// pinhole intrinsics, plus the clamp limits of tx/tz and ty/tz used for the Jacobian.
// Always scalars (shared by every lane).
template <typename T>
struct Camera {
  Mat3<T> R;
  Vec3<T> t;
  T fx, fy, cx, cy;
  T lim_xp, lim_xn, lim_yp, lim_yn;
  int width, height;
};

template <typename T>
HOST_DEVICE inline Camera<T> make_camera(const T* viewmat, const T* K, int width, int height) {
  Camera<T> c;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) c.R.m[i][j] = viewmat[i * 4 + j];
  c.t = {viewmat[3], viewmat[7], viewmat[11]};
  c.fx = K[0];
  c.fy = K[4];
  c.cx = K[2];
  c.cy = K[5];
  const T slack = T(kFrustumSlack);
  c.lim_xp = (T(width) - c.cx) / c.fx + slack * (T(0.5) * T(width) / c.fx);
  c.lim_xn = c.cx / c.fx + slack * (T(0.5) * T(width) / c.fx);
  c.lim_yp = (T(height) - c.cy) / c.fy + slack * (T(0.5) * T(height) / c.fy);
  c.lim_yn = c.cy / c.fy + slack * (T(0.5) * T(height) / c.fy);
  c.width = width;
  c.height = height;
  return c;
}

// v clamped to [lo, hi] (NaN stays NaN).
template <typename T>
LANE_INLINE T clamp_val(const T& v, LaneS<T> lo, LaneS<T> hi) {
  return sel(v < lo, splat_lanes<T>(lo), sel(v > hi, splat_lanes<T>(hi), v));
}

// One Gaussian's parameters (or one per lane).
template <typename T>
struct GaussianIn {
  Vec3<T> mean;
  T quat[4];   // (w, x, y, z), not necessarily normalised
  T scale[3];
};

template <typename T>
HOST_DEVICE inline GaussianIn<T> load_gaussian(const T* mean, const T* quat, const T* scale) {
  return {{mean[0], mean[1], mean[2]},
          {quat[0], quat[1], quat[2], quat[3]},
          {scale[0], scale[1], scale[2]}};
}

// Result of projecting one Gaussian (or one per lane). `radius` is an integer value
// (ceil), kept in the lane type; 0 where not visible, as every other field.
template <typename T>
struct Projection {
  LaneMask<T> visible;
  T mx, my;      // pixel coordinates of the projected mean
  T ca, cb, cc;  // conic: inverse 2D covariance [[ca, cb], [cb, cc]]
  T depth;       // camera-space z
  T radius;      // ceil(3 sqrt(λmax))
};

// Factor G = W M of the camera-space covariance W Σ Wᵀ = G Gᵀ of a Gaussian, where
// Σ = M Mᵀ and M = R_q diag(s). Also returns M's rotation R_q and the normalised
// quaternion (for the backward pass). Working with the factor (27 products) instead of
// forming Σ and W Σ Wᵀ (about 110) is the same matrix up to rounding.
template <typename T>
LANE_INLINE Mat3<T> covariance_factor(const Camera<LaneS<T>>& cam, const GaussianIn<T>& g,
                                      Mat3<T>& Rq, T qn[4], T& qnorm) {
  const T* q = g.quat;
  qnorm = lane_sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  for (int i = 0; i < 4; ++i) qn[i] = q[i] / qnorm;
  Rq = quat_to_rotmat(qn[0], qn[1], qn[2], qn[3]);
  Mat3<T> M;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) M.m[i][j] = Rq.m[i][j] * g.scale[j];
  return matmul(cam.R, M);
}

// Jacobian entries of the pinhole projection at the clamped tx/tz, ty/tz (3DGS).
template <typename T>
struct Jacobian {
  T j00, j02, j11, j12;
  LaneMask<T> clamp_x, clamp_y;  // whether tx/tz (ty/tz) hit a limit
  T txc, tyc;                    // tz · clamped ratio
};

template <typename T>
LANE_INLINE Jacobian<T> projection_jacobian(const Camera<LaneS<T>>& cam, const Vec3<T>& p) {
  Jacobian<T> J;
  const T rx = p.x / p.z, ry = p.y / p.z;
  J.clamp_x = (rx < -cam.lim_xn) | (rx > cam.lim_xp);
  J.clamp_y = (ry < -cam.lim_yn) | (ry > cam.lim_yp);
  J.txc = p.z * clamp_val(rx, -cam.lim_xn, cam.lim_xp);
  J.tyc = p.z * clamp_val(ry, -cam.lim_yn, cam.lim_yp);
  J.j00 = cam.fx / p.z;
  J.j02 = -cam.fx * J.txc / (p.z * p.z);
  J.j11 = cam.fy / p.z;
  J.j12 = -cam.fy * J.tyc / (p.z * p.z);
  return J;
}

// 2D covariance entries (a, b, c) = J Σc Jᵀ + 0.3 I = P Pᵀ + 0.3 I with P = J G (2x3);
// J row 0 = (j00, 0, j02), row 1 = (0, j11, j12).
template <typename T>
LANE_INLINE void covariance_2d(const Jacobian<T>& J, const Mat3<T>& G, T P[2][3], T& a, T& b,
                               T& c) {
  using S = LaneS<T>;
  for (int k = 0; k < 3; ++k) {
    P[0][k] = J.j00 * G.m[0][k] + J.j02 * G.m[2][k];
    P[1][k] = J.j11 * G.m[1][k] + J.j12 * G.m[2][k];
  }
  a = P[0][0] * P[0][0] + P[0][1] * P[0][1] + P[0][2] * P[0][2] + S(kLowpass);
  b = P[0][0] * P[1][0] + P[0][1] * P[1][1] + P[0][2] * P[1][2];
  c = P[1][0] * P[1][0] + P[1][1] * P[1][1] + P[1][2] * P[1][2] + S(kLowpass);
}

// Camera-space mean R m + t.
template <typename T>
LANE_INLINE Vec3<T> camera_point(const Camera<LaneS<T>>& cam, const Vec3<T>& mean) {
  const Vec3<T> p = matvec(cam.R, mean);
  return {p.x + cam.t.x, p.y + cam.t.y, p.z + cam.t.z};
}

// Forward projection and culling of one Gaussian (or one per lane). Everything is
// evaluated whatever the lane's fate (culled lanes may hold inf / NaN on the way, with
// no effect on the others); fields are zero where not visible.
template <typename T>
LANE_INLINE Projection<T> project_gaussian(const Camera<LaneS<T>>& cam, const GaussianIn<T>& g,
                                           LaneS<T> near_plane) {
  using S = LaneS<T>;
  const Vec3<T> pc = camera_point(cam, g.mean);
  Mat3<T> Rq;
  T qn[4], qnorm;
  const Mat3<T> G = covariance_factor(cam, g, Rq, qn, qnorm);
  const Jacobian<T> J = projection_jacobian(cam, pc);
  T P[2][3], a, b, c;
  covariance_2d(J, G, P, a, b, c);
  const T det = a * c - b * b;
  const T ca = c / det, cb = -b / det, cc = a / det;
  const T mx = cam.fx * pc.x / pc.z + cam.cx;
  const T my = cam.fy * pc.y / pc.z + cam.cy;
  const T mid = S(0.5) * (a + c);
  const T gap = mid * mid - det;
  const T lam = mid + lane_sqrt(sel(gap > S(kMinEigenGap), gap, splat_lanes<T>(S(kMinEigenGap))));
  T r = lane_ceil(S(3) * lane_sqrt(lam));
  r = sel(r > S(kMaxRadius), splat_lanes<T>(S(kMaxRadius)), r);
  const LaneMask<T> visible =
      (pc.z > near_plane) & (qnorm > S(0)) & lane_isfinite(a) & lane_isfinite(b) &
      lane_isfinite(c) & lane_isfinite(det) & (det > S(0)) & lane_isfinite(ca) &
      lane_isfinite(cb) & lane_isfinite(cc) & lane_isfinite(mx) & lane_isfinite(my) &
      lane_not((mx + r <= S(0)) | (mx - r >= S(cam.width)) | (my + r <= S(0)) |
               (my - r >= S(cam.height)));
  const T zero{};
  Projection<T> out;
  out.visible = visible;
  out.mx = sel(visible, mx, zero);
  out.my = sel(visible, my, zero);
  out.ca = sel(visible, ca, zero);
  out.cb = sel(visible, cb, zero);
  out.cc = sel(visible, cc, zero);
  out.depth = sel(visible, pc.z, zero);
  out.radius = sel(visible, r, zero);
  return out;
}

// Gradients of one Gaussian's parameters.
template <typename T>
struct GaussianGrad {
  Vec3<T> mean;
  T quat[4];
  T scale[3];
};

// Backward of project_gaussian for a visible Gaussian (or one per lane): dL/dmean,
// dL/dquat and dL/dscale from dL/dmeans2d (vmx, vmy), dL/dconic (vca, vcb, vcc) and
// dL/ddepth.
template <typename T>
LANE_INLINE GaussianGrad<T> project_gaussian_vjp(const Camera<LaneS<T>>& cam,
                                                 const GaussianIn<T>& g, const T& vmx,
                                                 const T& vmy, const T& vca, const T& vcb,
                                                 const T& vcc, const T& vdepth) {
  using S = LaneS<T>;
  const Vec3<T> pc = camera_point(cam, g.mean);
  Mat3<T> Rq;
  T qn[4], qnorm;
  const Mat3<T> G = covariance_factor(cam, g, Rq, qn, qnorm);
  const Jacobian<T> J = projection_jacobian(cam, pc);
  T P[2][3], a, b, c;
  covariance_2d(J, G, P, a, b, c);
  const T det = a * c - b * b;
  const T ca = c / det, cb = -b / det, cc = a / det;

  // Projected mean and depth.
  const T iz = S(1) / pc.z;
  T vtx = cam.fx * iz * vmx;
  T vty = cam.fy * iz * vmy;
  T vtz = -cam.fx * pc.x * iz * iz * vmx - cam.fy * pc.y * iz * iz * vmy + vdepth;

  // conic = inverse of [[a, b], [b, c]]: closed-form partial derivatives.
  const T va = -(ca * ca * vca + ca * cb * vcb + cb * cb * vcc);
  const T vb = -(S(2) * ca * cb * vca + (ca * cc + cb * cb) * vcb + S(2) * cb * cc * vcc);
  const T vc = -(cb * cb * vca + cb * cc * vcb + cc * cc * vcc);
  // Symmetric gradient V of the 2x2 covariance (b appears twice in the matrix).
  const T V00 = va, V01 = S(0.5) * vb, V11 = vc;

  // cov2d = P Pᵀ with P = J G:  dL/dP = 2 V P,  dL/dJ = dL/dP Gᵀ,  dL/dG = Jᵀ dL/dP.
  T vP[2][3];
  for (int k = 0; k < 3; ++k) {
    vP[0][k] = S(2) * (V00 * P[0][k] + V01 * P[1][k]);
    vP[1][k] = S(2) * (V01 * P[0][k] + V11 * P[1][k]);
  }
  // Only the four non-constant entries of J: (0, 0), (0, 2), (1, 1), (1, 2).
  T vJ[2][3];
  for (int i = 0; i < 2; ++i)
    for (int m = 0; m < 3; ++m)
      vJ[i][m] = vP[i][0] * G.m[m][0] + vP[i][1] * G.m[m][1] + vP[i][2] * G.m[m][2];
  // J entries as functions of the camera-space mean (with the 3DGS clamp): both cases
  // are evaluated, the clamp selects.
  vtz += -cam.fx * iz * iz * vJ[0][0] - cam.fy * iz * iz * vJ[1][1];
  {
    const T vtz_clamped = vtz + cam.fx * J.txc * iz * iz * iz * vJ[0][2];
    const T vtz_free = vtz + S(2) * cam.fx * pc.x * iz * iz * iz * vJ[0][2];
    vtx = sel(J.clamp_x, vtx, vtx + -cam.fx * iz * iz * vJ[0][2]);
    vtz = sel(J.clamp_x, vtz_clamped, vtz_free);
  }
  {
    const T vtz_clamped = vtz + cam.fy * J.tyc * iz * iz * iz * vJ[1][2];
    const T vtz_free = vtz + S(2) * cam.fy * pc.y * iz * iz * iz * vJ[1][2];
    vty = sel(J.clamp_y, vty, vty + -cam.fy * iz * iz * vJ[1][2]);
    vtz = sel(J.clamp_y, vtz_clamped, vtz_free);
  }
  GaussianGrad<T> out;
  // Camera-space mean = R m + t.
  const Mat3<S> Rt = transpose(cam.R);
  out.mean = matvec(Rt, Vec3<T>{vtx, vty, vtz});

  // G = W M → dL/dM = Wᵀ dL/dG.
  Mat3<T> vG;
  for (int k = 0; k < 3; ++k) {
    vG.m[0][k] = J.j00 * vP[0][k];
    vG.m[1][k] = J.j11 * vP[1][k];
    vG.m[2][k] = J.j02 * vP[0][k] + J.j12 * vP[1][k];
  }
  const Mat3<T> vM = matmul(Rt, vG);
  // M = R_q diag(s):  dL/dR_q[i][j] = dL/dM[i][j] s[j],  dL/ds[j] = Σ_i dL/dM[i][j] R_q[i][j].
  Mat3<T> vRq;
  for (int j = 0; j < 3; ++j) {
    T vs{};
    for (int i = 0; i < 3; ++i) {
      vRq.m[i][j] = vM.m[i][j] * g.scale[j];
      vs += vM.m[i][j] * Rq.m[i][j];
    }
    out.scale[j] = vs;
  }
  T vqn[4];
  quat_to_rotmat_vjp(qn[0], qn[1], qn[2], qn[3], vRq, vqn);
  // qn = q / |q|: project out the radial component.
  const T dot = qn[0] * vqn[0] + qn[1] * vqn[1] + qn[2] * vqn[2] + qn[3] * vqn[3];
  for (int i = 0; i < 4; ++i) out.quat[i] = (vqn[i] - qn[i] * dot) / qnorm;
  return out;
}

// ---------------------------------------------------------------------------------------
// Per-pixel blending.

// exp for the per-pixel Gaussian falloff. float: a branch-free Cephes-style evaluation
// (range reduction by ln 2 in two parts, degree-5 polynomial, exponent assembled from
// bits; measured relative error <= 8.4e-8 on [-87, 0]) that compilers can vectorise and
// that rounds identically in scalar and SIMD code (no FMA contraction: -ffp-contract=off).
// double: the library exp (the float64 path serves tests and gradcheck).
// The arithmetic core of gauss_exp(float) on a clamped argument, written once for a float
// and for a vector of floats (the SIMD twin in simd_isa_cpu.h calls it lane-wise): sets n
// to round(x / ln 2) and returns e^r for r = x - n ln 2 (so e^x = 2^n e^r).
template <typename V>
HOST_DEVICE inline V exp_reduced(const V& x, V& n) {
  const float shifter = 12582912.0f;  // 1.5 · 2^23: adding it rounds to an integer
  n = (x * 1.44269504088896341f + shifter) - shifter;
  const V r = (x - n * 0.693359375f) - n * -2.12194440e-4f;
  // The degree-5 polynomial by Estrin's scheme (shorter dependency chain than Horner's).
  const V r2 = r * r;
  const V p01 = r * 1.6666665459e-1f + 5.0000001201e-1f;
  const V p23 = r * 8.3334519073e-3f + 4.1665795894e-2f;
  const V p45 = r * 1.9875691500e-4f + 1.3981999507e-3f;
  const V p = (p01 + r2 * p23) + (r2 * r2) * p45;
  return p * r2 + r + 1.0f;
}

HOST_DEVICE inline float gauss_exp(float x) {
  x = x < 88.0f ? x : 88.0f;    // std::min(88, x), as the SIMD twin
  x = -87.0f < x ? x : -87.0f;  // std::max(-87, x)
  float n;
  const float y = exp_reduced(x, n);
  const int32_t bits = (static_cast<int32_t>(n) + 127) << 23;
#if defined(__CUDA_ARCH__)
  const float scale = __int_as_float(bits);
#else
  float scale;
  std::memcpy(&scale, &bits, sizeof(scale));
#endif
  return y * scale;
}

HOST_DEVICE inline double gauss_exp(double x) { return std::exp(x); }

// The Gaussian exponent at pixel offset (dx, dy) = pixel centre - mean.
template <typename T>
HOST_DEVICE inline T pixel_power(T ca, T cb, T cc, T dx, T dy) {
  return T(-0.5) * (ca * dx * dx + cc * dy * dy) - cb * dx * dy;
}

// Pixels a Gaussian can reach: a conservative box around the ellipse of pixel centres
// where α >= 1/255 is possible, plus a power threshold below which α < 1/255 is certain
// (so exp is skipped). The exact per-pair test always follows; these only prune.
// D is double or lanes of doubles (see the lane types above).
template <typename D>
struct BlendBound {
  LaneMask<D> never;  // opacity < 1/255 (or NaN): α < 1/255 at every pixel
  D power_reject;     // power < this ⇒ α < 1/255 (0 where never)
  // Pixel index box [x0, x1) x [y0, y1), integer values in [-2^30, 2^30]; the whole plane
  // when no tight bound is safe, empty (all 0) where never.
  D x0, x1, y0, y1;
};

// ln((double)(float) x): x rounded to float, then its natural logarithm evaluated with
// exactly rounded double operations only (no library call), so that the CPU and the CUDA
// kernels compute the same bits (library logs differ between the two in the last place,
// which could move a box edge of make_blend_bound by a pixel). Absolute error < 1e-12;
// zero, negative, infinite and NaN inputs give what std::log gives.
HOST_DEVICE inline double log_of_float(double v) {
  const double x = static_cast<double>(static_cast<float>(v));
  if (!(x > 0.0) || !(x < 3.5e38)) return std::log(x);  // special values are exact
  // x = m 2^e with m in [sqrt(1/2), sqrt(2)) (a float is a normal double: no subnormals).
  uint64_t bits;
#if defined(__CUDA_ARCH__)
  bits = static_cast<uint64_t>(__double_as_longlong(x));
#else
  std::memcpy(&bits, &x, sizeof(bits));
#endif
  int e = static_cast<int>((bits >> 52) & 0x7FF) - 1023;
  bits = (bits & 0x000FFFFFFFFFFFFFull) | 0x3FF0000000000000ull;  // m in [1, 2)
  double m;
#if defined(__CUDA_ARCH__)
  m = __longlong_as_double(static_cast<long long>(bits));
#else
  std::memcpy(&m, &bits, sizeof(m));
#endif
  if (m > 1.4142135623730951) {
    m = m * 0.5;
    e += 1;
  }
  // ln m = 2 atanh(s), s = (m - 1) / (m + 1), |s| < 0.1716: odd series to s^19.
  const double s = (m - 1.0) / (m + 1.0);
  const double s2 = s * s;
  double p = 1.0 / 19.0;
  p = p * s2 + 1.0 / 17.0;
  p = p * s2 + 1.0 / 15.0;
  p = p * s2 + 1.0 / 13.0;
  p = p * s2 + 1.0 / 11.0;
  p = p * s2 + 1.0 / 9.0;
  p = p * s2 + 1.0 / 7.0;
  p = p * s2 + 1.0 / 5.0;
  p = p * s2 + 1.0 / 3.0;
  p = p * s2 + 1.0;
  return static_cast<double>(e) * 0.6931471805599453 + 2.0 * s * p;
}

struct LogfFn {
  LANE_INLINE double operator()(double v) const { return log_of_float(v); }
};
template <typename D>
LANE_INLINE D lane_logf(const D& x) { return lane_map(x, LogfFn{}); }

// `eps` is the unit roundoff of the scalar type that evaluates pixel_power.
template <typename D>
LANE_INLINE BlendBound<D> make_blend_bound(const D& mx, const D& my, const D& ca, const D& cb,
                                           const D& cc, const D& opacity, double eps) {
  constexpr double kHuge = double(1 << 30);
  const D zero{};
  BlendBound<D> bb;
  bb.never = lane_not(opacity >= kAlphaMin);
  // α >= 1/255 needs power >= -L with L = log(255 o). The 1e-3 of slack leaves every
  // case where rounding could matter (α within 0.1% of 1/255) to the exact α test.
  // The log of the float-rounded 255 o (log_of_float: the same bits on the CPU and on
  // CUDA) is off by < 1e-6 here, far inside the 1e-3 of slack below.
  const D L = lane_logf(255.0 * opacity);
  bb.power_reject = sel(bb.never, zero, -L - 1e-3);
  const D det = ca * cc - cb * cb;
  const D lam_max = 0.5 * (ca + cc) + lane_sqrt(0.25 * (ca - cc) * (ca - cc) + cb * cb);
  // In the kernel's precision pixel_power is off by at most ~6 eps·cond·q (its cross
  // term can cancel the others), cond = λmax/λmin of the conic. Where that is below 1%,
  // the ellipse q = dᵀ conic d <= 2L widened by 5% holds every pixel centre the exact
  // test can accept; elsewhere no box is used.
  const D cond = lam_max * lam_max / det;
  const D two_l = 2.0 * L * 1.05 + 1e-4;
  const D hx = lane_sqrt(two_l * cc / det), hy = lane_sqrt(two_l * ca / det);
  // Pixel centre i + 0.5 within [m - h, m + h]. No spare pixel is needed: the 5% widening
  // dwarfs the rounding of these double expressions and of the kernel's dx.
  const D xl = lane_ceil(mx - 0.5 - hx), xh = lane_floor(mx - 0.5 + hx) + 1.0;
  const D yl = lane_ceil(my - 0.5 - hy), yh = lane_floor(my - 0.5 + hy) + 1.0;
  const LaneMask<D> tight = (ca > 0.0) & (det > 0.0) & lane_isfinite(L) &
                            lane_isfinite(lam_max) & (12.0 * eps * cond < 0.01) &
                            lane_isfinite(xl) & lane_isfinite(xh) & lane_isfinite(yl) &
                            lane_isfinite(yh);
  const D lo = splat_lanes<D>(-kHuge), hi = splat_lanes<D>(kHuge);
  bb.x0 = sel(bb.never, zero, sel(tight, clamp_val(xl, -kHuge, kHuge), lo));
  bb.x1 = sel(bb.never, zero, sel(tight, clamp_val(xh, -kHuge, kHuge), hi));
  bb.y0 = sel(bb.never, zero, sel(tight, clamp_val(yl, -kHuge, kHuge), lo));
  bb.y1 = sel(bb.never, zero, sel(tight, clamp_val(yh, -kHuge, kHuge), hi));
  return bb;
}

}  // namespace math
}  // namespace cobgs
