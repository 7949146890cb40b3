// CPU implementation of `ssim_mean_grad` (see blur.h): the mean SSIM of x against a fixed y
// and its gradient with respect to x, in one call. The element-wise parts (the five
// local statistics' products, the SSIM terms and the three per-pixel partial
// derivatives) run as fused loops over the planes; the blurs are gauss_blur's.
//
// With A1 = 2 μx μy + C1, A2 = 2 (E[xy] − μx μy) + C2, B1 = μx² + μy² + C1,
// B2 = (E[x²] − μx²) + (E[y²] − μy²) + C2 and S = A1 A2 / (B1 B2) per pixel,
//   ∂S/∂μx = 2 μy (A2 − A1) / (B1 B2) − 2 μx S (1/B1 − 1/B2),
//   ∂S/∂E[x²] = −S / B2,  ∂S/∂E[xy] = 2 A1 / (B1 B2),
//   d mean(S) / dx = (blur(∂S/∂μx) + 2 x blur(∂S/∂E[x²]) + y blur(∂S/∂E[xy])) / numel
// (the zero-padded symmetric blur is its own adjoint) — the formulas of cobgs/losses.py
// (_ssim_terms, _MeanSSIM), evaluated in the same order.
#include <torch/library.h>

#include "../common/checks.h"
#include "../common/parallel_cpu.h"
#include "blur.h"

namespace cobgs {
namespace {

constexpr double kC1 = 0.01 * 0.01;
constexpr double kC2 = 0.03 * 0.03;

template <typename T>
void ssim_kernel(const at::Tensor& x, const at::Tensor& y, const at::Tensor& g,
                 at::Tensor& mean_out, at::Tensor& grad) {
  const int64_t B = x.size(0), C = x.size(1), P = x.size(2) * x.size(3);
  const int64_t numel = B * C * P;
  // [B, 5C, H, W]: x, y, x², y², xy per batch (the layout _ssim_terms blurs).
  at::Tensor stats = at::empty({B, 5 * C, x.size(2), x.size(3)}, x.options());
  const T* xp = x.data_ptr<T>();
  const T* yp = y.data_ptr<T>();
  T* sp = stats.data_ptr<T>();
  const int64_t cp = C * P;  // one statistic of one batch item
  for (int64_t b = 0; b < B; ++b) {
    const T* xb = xp + b * cp;
    const T* yb = yp + b * cp;
    T* s = sp + b * 5 * cp;
#pragma omp parallel for simd schedule(static) num_threads(cpu_threads())
    for (int64_t k = 0; k < cp; ++k) {
      s[k] = xb[k];
      s[cp + k] = yb[k];
      s[2 * cp + k] = xb[k] * xb[k];
      s[3 * cp + k] = yb[k] * yb[k];
      s[4 * cp + k] = xb[k] * yb[k];
    }
  }
  const at::Tensor blurred = gauss_blur_cpu(stats, g);
  stats = at::Tensor();  // reuse its memory for the partial derivatives
  at::Tensor parts = at::empty({B, 3 * C, x.size(2), x.size(3)}, x.options());
  const T* bl = blurred.data_ptr<T>();
  T* dp = parts.data_ptr<T>();
  const T c1 = static_cast<T>(kC1), c2 = static_cast<T>(kC2);
  // The mean is accumulated in double; its last bits depend on the thread count (the
  // gradient does not use it, so training is unaffected).
  double total = 0.0;
  // Per batch item, a loop over its C·H·W positions (contiguous in every statistic).
  for (int64_t b = 0; b < B; ++b) {
    const T* s0 = bl + b * 5 * cp;
    T* d0 = dp + b * 3 * cp;
#pragma omp parallel for simd schedule(static) reduction(+ : total) \
    num_threads(cpu_threads())
    for (int64_t k = 0; k < cp; ++k) {
      const T* s = s0 + k;
      const T mu_x = s[0], mu_y = s[cp], exx = s[2 * cp], eyy = s[3 * cp], exy = s[4 * cp];
      const T a1 = T(2) * mu_x * mu_y + c1;
      const T a2 = T(2) * (exy - mu_x * mu_y) + c2;
      const T b1 = mu_x * mu_x + mu_y * mu_y + c1;
      const T b2 = (exx - mu_x * mu_x) + (eyy - mu_y * mu_y) + c2;
      const T inv_den = T(1) / (b1 * b2);
      const T smap = a1 * a2 * inv_den;
      total += static_cast<double>(a1 * a2 / (b1 * b2));
      T* d = d0 + k;
      d[0] = T(2) * mu_y * (a2 - a1) * inv_den - T(2) * mu_x * smap * (T(1) / b1 - T(1) / b2);
      d[cp] = -smap / b2;
      d[2 * cp] = T(2) * a1 * inv_den;
    }
  }
  const at::Tensor bparts = gauss_blur_cpu(parts, g);
  const T* bp = bparts.data_ptr<T>();
  T* gp = grad.data_ptr<T>();
  const T inv_n = T(1) / static_cast<T>(numel);
  for (int64_t b = 0; b < B; ++b) {
    const T* q0 = bp + b * 3 * cp;
    const T* xb = xp + b * cp;
    const T* yb = yp + b * cp;
    T* gb = gp + b * cp;
#pragma omp parallel for simd schedule(static) num_threads(cpu_threads())
    for (int64_t k = 0; k < cp; ++k)
      gb[k] = (q0[k] + T(2) * xb[k] * q0[cp + k] + yb[k] * q0[2 * cp + k]) * inv_n;
  }
  mean_out.fill_(total / static_cast<double>(numel));
}

}  // namespace

std::tuple<at::Tensor, at::Tensor> ssim_mean_grad_cpu(const at::Tensor& x, const at::Tensor& y,
                                                      const at::Tensor& g) {
  COBGS_CHECK_INPUT(x);
  COBGS_CHECK_INPUT(y);
  COBGS_CHECK_INPUT(g);
  TORCH_CHECK(x.scalar_type() == at::kFloat || x.scalar_type() == at::kDouble,
              "x must be float32 or float64, got ", x.scalar_type());
  TORCH_CHECK(x.dim() == 4, "x must have shape [B, C, H, W], got ", x.sizes());
  TORCH_CHECK(y.sizes() == x.sizes(), "y must have the shape of x ", x.sizes(), ", got ",
              y.sizes());
  COBGS_CHECK_DTYPE(y, x.scalar_type());
  COBGS_CHECK_DTYPE(g, x.scalar_type());
  TORCH_CHECK(x.numel() > 0, "x must not be empty");
  at::Tensor mean_out = at::empty({}, x.options());
  at::Tensor grad = at::empty_like(x);
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "cobgs::ssim_mean_grad",
                             [&] { ssim_kernel<scalar_t>(x, y, g, mean_out, grad); });
  return {mean_out, grad};
}

TORCH_LIBRARY_IMPL(cobgs, CPU, m) { m.impl("ssim_mean_grad", &ssim_mean_grad_cpu); }

}  // namespace cobgs
