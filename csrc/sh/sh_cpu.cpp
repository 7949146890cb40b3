// CPU implementation of the `sh_colors` op family (see sh.h). One Gaussian per loop
// iteration, split statically between OpenMP threads (results do not depend on the
// thread count). Replaces a chain of about 60 small ATen ops (and their autograd graph)
// per training iteration.
#include "sh.h"

#include <torch/library.h>

#include <algorithm>

#include "../common/checks.h"
#include "../common/parallel_cpu.h"
#include "../common/prof_cpu.h"
#include "../common/sh_math.h"

namespace cobgs {
namespace {

constexpr double kNormMin = 1e-12;  // as GaussianModel.colors: d / max(|d|, 1e-12)
constexpr int kMaxChannels = 16;    // per-Gaussian channel values live in registers

void check_sh_inputs(const at::Tensor& means, const at::Tensor& sh0, const at::Tensor& shN,
                     const at::Tensor& center, int64_t degree) {
  COBGS_CHECK_INPUT(means);
  COBGS_CHECK_INPUT(sh0);
  COBGS_CHECK_INPUT(shN);
  COBGS_CHECK_INPUT(center);
  TORCH_CHECK(means.scalar_type() == at::kFloat || means.scalar_type() == at::kDouble,
              "means must be float32 or float64, got ", means.scalar_type());
  TORCH_CHECK(means.dim() == 2, "means must have shape [N, 3], got ", means.sizes());
  TORCH_CHECK(sh0.dim() == 3, "sh0 must have shape [N, 1, C], got ", sh0.sizes());
  const int64_t n = means.size(0), c = sh0.size(2);
  TORCH_CHECK(c >= 1 && c <= kMaxChannels, "sh0 must have 1..", kMaxChannels,
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

// Unit direction from the camera centre; returns the clamped norm.
template <typename T>
inline T direction(const T* m, const T* c, T dir[3], T& norm) {
  const T d0 = m[0] - c[0], d1 = m[1] - c[1], d2 = m[2] - c[2];
  norm = std::sqrt(d0 * d0 + d1 * d1 + d2 * d2);
  const T nc = norm < T(kNormMin) ? T(kNormMin) : norm;
  dir[0] = d0 / nc;
  dir[1] = d1 / nc;
  dir[2] = d2 / nc;
  return nc;
}

// CC > 0 / DEG >= 0 fix the channel count / degree at compile time (the training case,
// RGB at degree 3: the loops unroll and the degree tests fold away); 0 / -1 read them
// from the arguments. Every instantiation performs the same operations in the same order.
template <typename T, int CC = 0, int DEG = -1>
void sh_forward(const T* means, const T* sh0, const T* shN, const T* center, int64_t n,
                int64_t M, int C_arg, int degree_arg, T* out) {
  const int C = CC > 0 ? CC : C_arg;
  const int degree = DEG >= 0 ? DEG : degree_arg;
  const int K = (degree + 1) * (degree + 1);
  COBGS_PROF_COUNT(kCallsSh, 1);
  COBGS_PROF_SCOPE(kShFwd);  // (the master thread only)
#pragma omp parallel for schedule(static) num_threads(cpu_threads())
  for (int64_t i = 0; i < n; ++i) {
    T Y[sh::kMaxCoeffs];
    if (degree > 0) {
      T dir[3], norm;
      direction(means + 3 * i, center, dir, norm);
      sh::basis(degree, dir[0], dir[1], dir[2], Y);
    }
    const T* c0 = sh0 + i * C;
    const T* cn = shN + i * M * C;
    T v[kMaxChannels];
    for (int ch = 0; ch < C; ++ch) v[ch] = c0[ch] * T(sh::kC0);
    // Coefficients in memory order (k outer); each channel still sums k = 0, 1, ...
    for (int k = 1; k < K; ++k)
      for (int ch = 0; ch < C; ++ch) v[ch] += Y[k] * cn[(k - 1) * C + ch];
    for (int ch = 0; ch < C; ++ch) {
      const T u = v[ch] + T(0.5);
      out[i * C + ch] = u < T(0) ? T(0) : u;  // clamp_min(0); NaN stays NaN
    }
  }
}

template <typename T, int CC = 0, int DEG = -1>
void sh_backward(const T* means, const T* sh0, const T* shN, const T* center, int64_t n,
                 int64_t M, int C_arg, int degree_arg, const T* v_col, T* v_means, T* v_sh0,
                 T* v_shN) {
  const int C = CC > 0 ? CC : C_arg;
  const int degree = DEG >= 0 ? DEG : degree_arg;
  const int K = (degree + 1) * (degree + 1);
  COBGS_PROF_COUNT(kCallsShBwd, 1);
  COBGS_PROF_SCOPE(kShBwd);  // (the master thread only)
#pragma omp parallel for schedule(static) num_threads(cpu_threads())
  for (int64_t i = 0; i < n; ++i) {
    T* g0 = v_sh0 + i * C;
    T* gn = v_shN + i * M * C;
    bool any_grad = false;
    for (int ch = 0; ch < C; ++ch) any_grad |= v_col[i * C + ch] != T(0);
    if (!any_grad) {  // e.g. a Gaussian hidden in this view: every gradient is zero
      std::fill(g0, g0 + C, T(0));
      std::fill(gn, gn + M * C, T(0));
      v_means[3 * i] = v_means[3 * i + 1] = v_means[3 * i + 2] = T(0);
      continue;
    }
    T Y[sh::kMaxCoeffs], dir[3], norm = T(0), nc = T(1);
    if (degree > 0) {
      nc = direction(means + 3 * i, center, dir, norm);
      sh::basis(degree, dir[0], dir[1], dir[2], Y);
    }
    const T* c0 = sh0 + i * C;
    const T* cn = shN + i * M * C;
    T w[sh::kMaxCoeffs];  // Σ_ch c_k[ch] · dL/dv[ch]
    T v[kMaxChannels], g[kMaxChannels];
    for (int ch = 0; ch < C; ++ch) v[ch] = c0[ch] * T(sh::kC0);
    for (int k = 1; k < K; ++k)
      for (int ch = 0; ch < C; ++ch) v[ch] += Y[k] * cn[(k - 1) * C + ch];
    for (int ch = 0; ch < C; ++ch) {
      // clamp_min's gradient mask (the gradient passes where v + 0.5 >= 0)
      g[ch] = v[ch] + T(0.5) >= T(0) ? v_col[i * C + ch] : T(0);
      g0[ch] = g[ch] * T(sh::kC0);
    }
    for (int k = 1; k < K; ++k) {
      const T* ck = cn + (k - 1) * C;
      T* gk = gn + (k - 1) * C;
      T wk = T(0);
      for (int ch = 0; ch < C; ++ch) {
        gk[ch] = g[ch] * Y[k];
        wk += ck[ch] * g[ch];
      }
      w[k] = wk;
    }
    for (int64_t k = (K - 1) * C; k < M * C; ++k) gn[k] = T(0);
    if (degree == 0) {
      v_means[3 * i] = v_means[3 * i + 1] = v_means[3 * i + 2] = T(0);
      continue;
    }
    T vd[3];
    sh::basis_vjp(degree, dir[0], dir[1], dir[2], w, vd);
    // dir = d / max(|d|, eps): project out the radial part (unless the clamp is active).
    const T dot = norm >= T(kNormMin) ? dir[0] * vd[0] + dir[1] * vd[1] + dir[2] * vd[2] : T(0);
    for (int a = 0; a < 3; ++a) v_means[3 * i + a] = (vd[a] - dir[a] * dot) / nc;
  }
}

}  // namespace

at::Tensor sh_colors_cpu(const at::Tensor& means, const at::Tensor& sh0, const at::Tensor& shN,
                         const at::Tensor& center, int64_t degree) {
  check_sh_inputs(means, sh0, shN, center, degree);
  const int64_t n = means.size(0), M = shN.size(1), C = sh0.size(2);
  at::Tensor out = at::empty({n, C}, means.options());
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "cobgs::sh_colors", [&] {
    auto fn = C == 3 && degree == 3 ? &sh_forward<scalar_t, 3, 3> : &sh_forward<scalar_t>;
    fn(means.data_ptr<scalar_t>(), sh0.data_ptr<scalar_t>(), shN.data_ptr<scalar_t>(),
       center.data_ptr<scalar_t>(), n, M, static_cast<int>(C), static_cast<int>(degree),
       out.data_ptr<scalar_t>());
  });
  return out;
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> sh_colors_bwd_cpu(
    const at::Tensor& means, const at::Tensor& sh0, const at::Tensor& shN,
    const at::Tensor& center, int64_t degree, const at::Tensor& v_colors) {
  check_sh_inputs(means, sh0, shN, center, degree);
  const int64_t n = means.size(0), M = shN.size(1), C = sh0.size(2);
  COBGS_CHECK_INPUT(v_colors);
  COBGS_CHECK_DTYPE(v_colors, means.scalar_type());
  COBGS_CHECK_SHAPE(v_colors, n, C);
  // Every element is written by the kernel (no zero fill needed).
  at::Tensor v_means = at::empty_like(means);
  at::Tensor v_sh0 = at::empty_like(sh0);
  at::Tensor v_shN = at::empty_like(shN);
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "cobgs::sh_colors_bwd", [&] {
    auto fn = C == 3 && degree == 3 ? &sh_backward<scalar_t, 3, 3> : &sh_backward<scalar_t>;
    fn(means.data_ptr<scalar_t>(), sh0.data_ptr<scalar_t>(), shN.data_ptr<scalar_t>(),
       center.data_ptr<scalar_t>(), n, M, static_cast<int>(C), static_cast<int>(degree),
       v_colors.data_ptr<scalar_t>(), v_means.data_ptr<scalar_t>(), v_sh0.data_ptr<scalar_t>(),
       v_shN.data_ptr<scalar_t>());
  });
  return {v_means, v_sh0, v_shN};
}

TORCH_LIBRARY_IMPL(cobgs, CPU, m) {
  m.impl("sh_colors", &sh_colors_cpu);
  m.impl("sh_colors_bwd", &sh_colors_bwd_cpu);
}

}  // namespace cobgs
