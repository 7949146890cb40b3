// CPU implementation of `ssim_mean_grad` (see blur.h): the mean SSIM of x against a fixed y
// and its gradient with respect to x, in one call. The element-wise parts (the five
// local statistics' products, the SSIM terms and the three per-pixel partial
// derivatives) are fused into the blur's row passes (csrc/blur/blur_rows_cpu.h): the
// statistics are blurred straight from x and y, and only the three partials are stored.
//
// With A1 = 2 μx μy + C1, A2 = 2 (E[xy] − μx μy) + C2, B1 = μx² + μy² + C1,
// B2 = (E[x²] − μx²) + (E[y²] − μy²) + C2 and S = A1 A2 / (B1 B2) per pixel,
//   ∂S/∂μx = 2 μy (A2 − A1) / (B1 B2) − 2 μx S (1/B1 − 1/B2),
//   ∂S/∂E[x²] = −S / B2,  ∂S/∂E[xy] = 2 A1 / (B1 B2),
//   d mean(S) / dx = (blur(∂S/∂μx) + 2 x blur(∂S/∂E[x²]) + y blur(∂S/∂E[xy])) / numel
// (the zero-padded symmetric blur is its own adjoint) — the formulas of cobgs/train/losses.py
// (_ssim_terms, _MeanSSIM), evaluated in the same order.
#include <torch/library.h>

#include "../common/checks.h"
#include "blur.h"

namespace cobgs {

std::tuple<at::Tensor, at::Tensor> ssim_mean_grad_cpu(const at::Tensor& x, const at::Tensor& y,
                                                      const at::Tensor& g) {
  COBGS_CHECK_CPU(x);
  check_ssim_inputs(x, y, g);
  const int64_t planes = x.size(0) * x.size(1);
  const int H = static_cast<int>(x.size(2)), W = static_cast<int>(x.size(3));
  at::Tensor grad = at::empty_like(x);
  at::Tensor parts = at::empty({3, planes, H, W}, x.options());
  double total = 0.0;
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "cobgs::ssim_mean_grad", [&] {
    total = blur_detail::ssim_mean_grad_planes<scalar_t>(
        x.data_ptr<scalar_t>(), y.data_ptr<scalar_t>(), planes, H, W, g.data_ptr<scalar_t>(),
        static_cast<int>(g.size(0)), parts.data_ptr<scalar_t>(), grad.data_ptr<scalar_t>());
  });
  at::Tensor mean_out = at::empty({}, x.options());
  mean_out.fill_(total / static_cast<double>(x.numel()));
  return {mean_out, grad};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> photometric_loss_grad_cpu(const at::Tensor& img,
                                                                        const at::Tensor& ref,
                                                                        const at::Tensor& g,
                                                                        double ssim_weight) {
  COBGS_CHECK_CPU(img);
  check_photometric_inputs(img, ref, g, ssim_weight);
  const int64_t d = img.dim();
  const int64_t batch = d == 4 ? img.size(0) : 1;
  const int H = static_cast<int>(img.size(d - 3)), W = static_cast<int>(img.size(d - 2));
  const int C = static_cast<int>(img.size(d - 1));
  const double numel = static_cast<double>(img.numel());
  at::Tensor grad = at::empty_like(img);
  at::Tensor parts = at::empty({3, img.numel()}, img.options());
  double ssim_sum = 0.0, l1_sum = 0.0;
  AT_DISPATCH_FLOATING_TYPES(img.scalar_type(), "cobgs::photometric_loss_grad", [&] {
    // dL/dx = (1 − λ)/numel · sign(x − y) − λ · d mean(S)/dx
    ssim_sum = blur_detail::photometric_grad_rows<scalar_t>(
        img.data_ptr<scalar_t>(), ref.data_ptr<scalar_t>(), batch, H, W, C,
        g.data_ptr<scalar_t>(), static_cast<int>(g.size(0)), parts.data_ptr<scalar_t>(),
        grad.data_ptr<scalar_t>(), (1.0 - ssim_weight) / numel, -ssim_weight, &l1_sum);
  });
  at::Tensor l1 = at::empty({}, img.options()).fill_(l1_sum / numel);
  at::Tensor ssim = at::empty({}, img.options()).fill_(ssim_sum / numel);
  return {l1, ssim, grad};
}

TORCH_LIBRARY_IMPL(cobgs, CPU, m) {
  m.impl("ssim_mean_grad", &ssim_mean_grad_cpu);
  m.impl("photometric_loss_grad", &photometric_loss_grad_cpu);
}

}  // namespace cobgs
