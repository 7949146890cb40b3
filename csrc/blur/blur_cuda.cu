// CUDA implementation of the `gauss_blur` op family (see blur.h): the separable zero-padded
// blur, the fused SSIM mean + gradient and the photometric loss, with the CPU kernels'
// per-value operation order (blur_rows_cpu.h: vertical taps over the rows inside the
// image, then horizontal taps t = 0 .. n-1 over a zero-padded row; built with
// --fmad=false), so every per-pixel value has the CPU's bits. Each pass is one thread per
// value; the means are sums in double over those values (order-dependent rounding only).
//
// Images are `planes` planes of H rows of R values whose horizontal taps are `step` values
// apart: planar [B, K, H, W] has R = W, step = 1; channel-last [B, H, W, C] (the
// renderer's layout) has R = W·C, step = C.
#include <torch/library.h>

#include "../common/cuda_common.cuh"
#include "blur.h"
#include "ssim_math.h"

namespace cobgs {
namespace {

constexpr int kThreads = 256;

struct Geometry {
  int64_t planes;
  int H, R, step, n;
  __host__ __device__ int64_t size() const { return planes * H * R; }
};

// The vertical taps of value e: t in [t0, t1) reads the value at first + t R (the rows
// inside the image only).
struct Taps {
  int t0, t1;
  int64_t first;
};

__device__ __forceinline__ Taps vertical_taps(const Geometry& d, int64_t e) {
  const int64_t plane_row = e / d.R;
  const int j = static_cast<int>(e % d.R);
  const int i = static_cast<int>(plane_row % d.H);
  const int64_t p = plane_row / d.H;
  const int pad = d.n / 2;
  Taps v;
  v.t0 = pad - i > 0 ? pad - i : 0;
  v.t1 = d.n < d.H + pad - i ? d.n : d.H + pad - i;
  v.first = (p * d.H + (i - pad)) * d.R + j;  // the row of tap t = 0 (may lie outside)
  return v;
}

// out[k] = Σ_t g[t] src[k][row + t - n/2] over the rows inside the image (K planes, `kst`
// values apart in src and out).
template <typename T, int K>
__global__ void vertical_kernel(Geometry d, const T* __restrict__ src, int64_t kst,
                                const T* __restrict__ g, T* __restrict__ out) {
  const int64_t e = blockIdx.x * int64_t(kThreads) + threadIdx.x;
  if (e >= d.size()) return;
  const Taps v = vertical_taps(d, e);
  T acc[K];
  for (int k = 0; k < K; ++k) acc[k] = T(0);
  for (int t = v.t0; t < v.t1; ++t) {
    const int64_t o = v.first + int64_t(t) * d.R;
    for (int k = 0; k < K; ++k) acc[k] += g[t] * src[k * kst + o];
  }
  for (int k = 0; k < K; ++k) out[k * kst + e] = acc[k];
}

// The vertical pass of the five SSIM statistics x, y, x², y², xy (products per tap).
template <typename T>
__global__ void vertical_stats_kernel(Geometry d, const T* __restrict__ x,
                                      const T* __restrict__ y, const T* __restrict__ g,
                                      T* __restrict__ out) {
  const int64_t e = blockIdx.x * int64_t(kThreads) + threadIdx.x;
  const int64_t size = d.size();
  if (e >= size) return;
  const Taps v = vertical_taps(d, e);
  T acc[5] = {T(0), T(0), T(0), T(0), T(0)};
  for (int t = v.t0; t < v.t1; ++t) {
    const T w = g[t];
    const int64_t o = v.first + int64_t(t) * d.R;
    const T xv = x[o], yv = y[o];
    acc[0] += w * xv;
    acc[1] += w * yv;
    acc[2] += w * (xv * xv);
    acc[3] += w * (yv * yv);
    acc[4] += w * (xv * yv);
  }
  for (int k = 0; k < 5; ++k) out[k * size + e] = acc[k];
}

// h[k] = Σ_t g[t] row_k[j + (t - n/2) step], zero outside the row.
template <typename T, int K>
__device__ __forceinline__ void horizontal(const Geometry& d, const T* __restrict__ src,
                                           int64_t kst, const T* __restrict__ g, int64_t e,
                                           T* h) {
  const int j = static_cast<int>(e % d.R);
  const int pad = (d.n / 2) * d.step;
  for (int k = 0; k < K; ++k) h[k] = T(0);
  for (int t = 0; t < d.n; ++t) {
    const int jj = j + t * d.step - pad;
    const bool in = jj >= 0 && jj < d.R;
    for (int k = 0; k < K; ++k) h[k] += g[t] * (in ? src[k * kst + e + (jj - j)] : T(0));
  }
}

template <typename T>
__global__ void horizontal_kernel(Geometry d, const T* __restrict__ src,
                                  const T* __restrict__ g, T* __restrict__ out) {
  const int64_t e = blockIdx.x * int64_t(kThreads) + threadIdx.x;
  if (e >= d.size()) return;
  T h[1];
  horizontal<T, 1>(d, src, 0, g, e, h);
  out[e] = h[0];
}

// The SSIM terms of every value from its blurred statistics: the three partials
// ∂S/∂μx, ∂S/∂E[x²], ∂S/∂E[xy] (formulas: ssim_cpu.cpp) and S itself.
template <typename T>
__global__ void ssim_terms_kernel(Geometry d, const T* __restrict__ stats,
                                  const T* __restrict__ g, T c1, T c2, T* __restrict__ parts,
                                  T* __restrict__ smap_out) {
  const int64_t e = blockIdx.x * int64_t(kThreads) + threadIdx.x;
  const int64_t size = d.size();
  if (e >= size) return;
  T s[5];
  horizontal<T, 5>(d, stats, size, g, e, s);
  const ssim::Terms<T> t = ssim::terms<T, T>(s[0], s[1], s[2], s[3], s[4], c1, c2);
  smap_out[e] = t.s;
  parts[e] = t.d_mu;
  parts[size + e] = t.d_xx;
  parts[2 * size + e] = t.d_xy;
}

// grad = w_l1 sign(x - y) + w_ssim (b0 + 2 x b1 + y b2) / numel, b = the blurred partials
// (kL1 false: w_l1 = 0 and w_ssim = 1, no |x - y|).
template <typename T, bool kL1>
__global__ void ssim_grad_kernel(Geometry d, const T* __restrict__ vparts,
                                 const T* __restrict__ g, const T* __restrict__ x,
                                 const T* __restrict__ y, T inv_n, T w_l1, T w_ssim,
                                 T* __restrict__ grad, T* __restrict__ absdiff) {
  const int64_t e = blockIdx.x * int64_t(kThreads) + threadIdx.x;
  const int64_t size = d.size();
  if (e >= size) return;
  T q[3];
  horizontal<T, 3>(d, vparts, size, g, e, q);
  const T xv = x[e], yv = y[e];
  const T ssim_grad = ssim::grad<T, T>(q, xv, yv, inv_n);
  if (kL1) {
    const T diff = xv - yv;
    grad[e] = w_l1 * ssim::sign<T, T>(diff) + w_ssim * ssim_grad;
    absdiff[e] = ssim::abs<T, T>(diff);
  } else {
    grad[e] = ssim_grad;
  }
}

// The SSIM passes on x, y; writes grad and returns (Σ S, Σ |x - y|) as double tensors.
template <typename T, bool kL1>
std::pair<at::Tensor, at::Tensor> ssim_passes(const Geometry& d, const at::Tensor& x,
                                              const at::Tensor& y, const at::Tensor& g,
                                              at::Tensor& grad, double w_l1, double w_ssim) {
  const int64_t size = d.size();
  const auto opts = x.options();
  const auto grid = cuda::blocks_for(size, kThreads);
  const T* gp = g.data_ptr<T>();
  at::Tensor stats = at::empty({5, size}, opts);
  vertical_stats_kernel<T><<<grid, kThreads, 0, cuda::stream()>>>(d, x.data_ptr<T>(),
                                                                   y.data_ptr<T>(), gp,
                                                                   stats.data_ptr<T>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  at::Tensor parts = at::empty({3, size}, opts);
  at::Tensor smap = at::empty({size}, opts);
  ssim_terms_kernel<T><<<grid, kThreads, 0, cuda::stream()>>>(
      d, stats.data_ptr<T>(), gp, static_cast<T>(kSsimC1), static_cast<T>(kSsimC2),
      parts.data_ptr<T>(), smap.data_ptr<T>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  at::Tensor vparts = at::empty({3, size}, opts);
  vertical_kernel<T, 3><<<grid, kThreads, 0, cuda::stream()>>>(d, parts.data_ptr<T>(), size,
                                                                gp, vparts.data_ptr<T>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  at::Tensor absdiff = kL1 ? at::empty({size}, opts) : at::empty({0}, opts);
  ssim_grad_kernel<T, kL1><<<grid, kThreads, 0, cuda::stream()>>>(
      d, vparts.data_ptr<T>(), gp, x.data_ptr<T>(), y.data_ptr<T>(),
      T(1) / static_cast<T>(size), static_cast<T>(w_l1), static_cast<T>(w_ssim),
      grad.data_ptr<T>(), absdiff.data_ptr<T>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return {smap.to(at::kDouble).sum(), kL1 ? absdiff.to(at::kDouble).sum() : at::Tensor()};
}

}  // namespace

at::Tensor gauss_blur_cuda(const at::Tensor& x, const at::Tensor& g) {
  TORCH_CHECK(x.is_cuda(), "x must be a CUDA tensor, got ", x.device());
  check_blur_inputs(x, g);
  const c10::cuda::CUDAGuard guard(x.device());
  at::Tensor y = at::empty_like(x);
  if (x.numel() == 0) return y;
  const Geometry d{x.size(0) * x.size(1), static_cast<int>(x.size(2)),
                   static_cast<int>(x.size(3)), 1, static_cast<int>(g.size(0))};
  at::Tensor vert = at::empty_like(x);
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "cobgs::gauss_blur_cuda", [&] {
    const auto grid = cuda::blocks_for(d.size(), kThreads);
    vertical_kernel<scalar_t, 1><<<grid, kThreads, 0, cuda::stream()>>>(
        d, x.data_ptr<scalar_t>(), 0, g.data_ptr<scalar_t>(), vert.data_ptr<scalar_t>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
    horizontal_kernel<scalar_t><<<grid, kThreads, 0, cuda::stream()>>>(
        d, vert.data_ptr<scalar_t>(), g.data_ptr<scalar_t>(), y.data_ptr<scalar_t>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return y;
}

std::tuple<at::Tensor, at::Tensor> ssim_mean_grad_cuda(const at::Tensor& x, const at::Tensor& y,
                                                       const at::Tensor& g) {
  TORCH_CHECK(x.is_cuda(), "x must be a CUDA tensor, got ", x.device());
  check_ssim_inputs(x, y, g);
  const c10::cuda::CUDAGuard guard(x.device());
  const Geometry d{x.size(0) * x.size(1), static_cast<int>(x.size(2)),
                   static_cast<int>(x.size(3)), 1, static_cast<int>(g.size(0))};
  at::Tensor grad = at::empty_like(x);
  at::Tensor total;
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "cobgs::ssim_mean_grad_cuda", [&] {
    total = ssim_passes<scalar_t, false>(d, x, y, g, grad, 0.0, 1.0).first;
  });
  return {(total / static_cast<double>(x.numel())).to(x.scalar_type()), grad};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> photometric_loss_grad_cuda(const at::Tensor& img,
                                                                         const at::Tensor& ref,
                                                                         const at::Tensor& g,
                                                                         double ssim_weight) {
  TORCH_CHECK(img.is_cuda(), "img must be a CUDA tensor, got ", img.device());
  check_photometric_inputs(img, ref, g, ssim_weight);
  const c10::cuda::CUDAGuard guard(img.device());
  const int64_t dims = img.dim();
  const int64_t batch = dims == 4 ? img.size(0) : 1;
  const int H = static_cast<int>(img.size(dims - 3)), W = static_cast<int>(img.size(dims - 2));
  const int C = static_cast<int>(img.size(dims - 1));
  const Geometry d{batch, H, W * C, C, static_cast<int>(g.size(0))};
  const double numel = static_cast<double>(img.numel());
  at::Tensor grad = at::empty_like(img);
  std::pair<at::Tensor, at::Tensor> sums;
  AT_DISPATCH_FLOATING_TYPES(img.scalar_type(), "cobgs::photometric_loss_grad_cuda", [&] {
    // dL/dx = (1 − λ)/numel · sign(x − y) − λ · d mean(S)/dx
    sums = ssim_passes<scalar_t, true>(d, img, ref, g, grad, (1.0 - ssim_weight) / numel,
                                       -ssim_weight);
  });
  return {(sums.second / numel).to(img.scalar_type()),
          (sums.first / numel).to(img.scalar_type()), grad};
}

TORCH_LIBRARY_IMPL(cobgs, CUDA, m) {
  m.impl("gauss_blur", &gauss_blur_cuda);
  m.impl("ssim_mean_grad", &ssim_mean_grad_cuda);
  m.impl("photometric_loss_grad", &photometric_loss_grad_cuda);
}

}  // namespace cobgs
