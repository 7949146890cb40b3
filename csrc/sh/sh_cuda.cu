// CUDA implementation of the `sh_colors` op family (see sh.h): one thread per Gaussian
// through the per-Gaussian code the CPU loops use (sh_one.h, formulas in sh_math.h),
// compiled without FMA contraction so that each output has the CPU's bits.
#include <torch/library.h>

#include "../common/cuda_common.cuh"
#include "sh.h"
#include "sh_one.h"

namespace cobgs {
namespace {

constexpr int kThreads = 128;

template <typename T, int CC, int DEG>
__global__ void __launch_bounds__(kThreads) sh_forward_kernel(ShArgs<T> a, int64_t n) {
  const int64_t i = blockIdx.x * int64_t(kThreads) + threadIdx.x;
  if (i < n) sh_forward_one<T, CC, DEG>(a, i);
}

template <typename T, int CC, int DEG>
__global__ void __launch_bounds__(kThreads) sh_backward_kernel(ShBwdArgs<T> a, int64_t n) {
  const int64_t i = blockIdx.x * int64_t(kThreads) + threadIdx.x;
  if (i < n) sh_backward_one<T, CC, DEG>(a, i);
}

}  // namespace

at::Tensor sh_colors_cuda(const at::Tensor& means, const at::Tensor& sh0, const at::Tensor& shN,
                          const at::Tensor& center, int64_t degree) {
  TORCH_CHECK(means.is_cuda(), "means must be a CUDA tensor, got ", means.device());
  check_sh_inputs(means, sh0, shN, center, degree);
  const c10::cuda::CUDAGuard guard(means.device());
  const int64_t n = means.size(0), M = shN.size(1), C = sh0.size(2);
  at::Tensor out = at::empty({n, C}, means.options());
  if (n == 0) return out;
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "cobgs::sh_colors_cuda", [&] {
    const ShArgs<scalar_t> a{means.data_ptr<scalar_t>(), sh0.data_ptr<scalar_t>(),
                             shN.data_ptr<scalar_t>(),   center.data_ptr<scalar_t>(),
                             M, static_cast<int>(C), static_cast<int>(degree),
                             out.data_ptr<scalar_t>()};
    const auto grid = cuda::blocks_for(n, kThreads);
    if (C == 3 && degree == 3)  // the training case: fixed sizes, arrays in registers
      sh_forward_kernel<scalar_t, 3, 3><<<grid, kThreads, 0, cuda::stream()>>>(a, n);
    else
      sh_forward_kernel<scalar_t, 0, -1><<<grid, kThreads, 0, cuda::stream()>>>(a, n);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return out;
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> sh_colors_bwd_cuda(
    const at::Tensor& means, const at::Tensor& sh0, const at::Tensor& shN,
    const at::Tensor& center, int64_t degree, const at::Tensor& v_colors) {
  TORCH_CHECK(means.is_cuda(), "means must be a CUDA tensor, got ", means.device());
  check_sh_inputs(means, sh0, shN, center, degree);
  check_sh_bwd_input(means, sh0, v_colors);
  const c10::cuda::CUDAGuard guard(means.device());
  const int64_t n = means.size(0), M = shN.size(1), C = sh0.size(2);
  at::Tensor v_means = at::empty_like(means);
  at::Tensor v_sh0 = at::empty_like(sh0);
  at::Tensor v_shN = at::empty_like(shN);
  if (n == 0) return {v_means, v_sh0, v_shN};
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "cobgs::sh_colors_bwd_cuda", [&] {
    const ShBwdArgs<scalar_t> a{means.data_ptr<scalar_t>(),  sh0.data_ptr<scalar_t>(),
                                shN.data_ptr<scalar_t>(),    center.data_ptr<scalar_t>(),
                                M,                           static_cast<int>(C),
                                static_cast<int>(degree),    v_colors.data_ptr<scalar_t>(),
                                v_means.data_ptr<scalar_t>(), v_sh0.data_ptr<scalar_t>(),
                                v_shN.data_ptr<scalar_t>()};
    const auto grid = cuda::blocks_for(n, kThreads);
    if (C == 3 && degree == 3)
      sh_backward_kernel<scalar_t, 3, 3><<<grid, kThreads, 0, cuda::stream()>>>(a, n);
    else
      sh_backward_kernel<scalar_t, 0, -1><<<grid, kThreads, 0, cuda::stream()>>>(a, n);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return {v_means, v_sh0, v_shN};
}

TORCH_LIBRARY_IMPL(cobgs, CUDA, m) {
  m.impl("sh_colors", &sh_colors_cuda);
  m.impl("sh_colors_bwd", &sh_colors_bwd_cuda);
}

}  // namespace cobgs
