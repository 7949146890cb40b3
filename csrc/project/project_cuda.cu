// CUDA implementation of the `project` op family (see project.h): one thread per Gaussian
// through the formulas of csrc/common/gs_math.h, the CPU kernels' own (compiled without
// FMA contraction, --fmad=false, so each output has the CPU's bits).
#include <torch/library.h>

#include "../common/cuda_common.cuh"
#include "../common/gs_math.h"
#include "project.h"

namespace cobgs {
namespace {

constexpr int kThreads = 256;

// The camera of the launch, built once per block from the [4, 4] / [3, 3] device tensors.
template <typename T>
__device__ __forceinline__ const math::Camera<T>& block_camera(const T* viewmat, const T* K,
                                                               int width, int height) {
  __shared__ math::Camera<T> cam;
  if (threadIdx.x == 0) cam = math::make_camera<T>(viewmat, K, width, height);
  __syncthreads();
  return cam;
}

template <typename T>
__global__ void __launch_bounds__(kThreads)
    project_kernel(int64_t n, const T* __restrict__ viewmat, const T* __restrict__ K,
                   int width, int height, T near_plane, const T* __restrict__ means,
                   const T* __restrict__ quats, const T* __restrict__ scales,
                   T* __restrict__ means2d, T* __restrict__ conics, T* __restrict__ depths,
                   int32_t* __restrict__ radii) {
  const math::Camera<T>& cam = block_camera(viewmat, K, width, height);
  const int64_t i = blockIdx.x * int64_t(kThreads) + threadIdx.x;
  if (i >= n) return;
  const auto g = math::load_gaussian<T>(means + 3 * i, quats + 4 * i, scales + 3 * i);
  const math::Projection<T> p = math::project_gaussian<T>(cam, g, near_plane);
  means2d[2 * i] = p.mx;
  means2d[2 * i + 1] = p.my;
  conics[3 * i] = p.ca;
  conics[3 * i + 1] = p.cb;
  conics[3 * i + 2] = p.cc;
  depths[i] = p.depth;
  radii[i] = static_cast<int32_t>(p.radius);
}

template <typename T>
__global__ void __launch_bounds__(kThreads)
    project_bwd_kernel(int64_t n, const T* __restrict__ viewmat, const T* __restrict__ K,
                       int width, int height, const T* __restrict__ means,
                       const T* __restrict__ quats, const T* __restrict__ scales,
                       const int32_t* __restrict__ radii, const T* __restrict__ v_means2d,
                       const T* __restrict__ v_conics, const T* __restrict__ v_depths,
                       T* __restrict__ v_means, T* __restrict__ v_quats,
                       T* __restrict__ v_scales) {
  const math::Camera<T>& cam = block_camera(viewmat, K, width, height);
  const int64_t i = blockIdx.x * int64_t(kThreads) + threadIdx.x;
  if (i >= n) return;
  const T vmx = v_means2d[2 * i], vmy = v_means2d[2 * i + 1];
  const T vca = v_conics[3 * i], vcb = v_conics[3 * i + 1], vcc = v_conics[3 * i + 2];
  const T vd = v_depths[i];
  T* om = v_means + 3 * i;
  T* oq = v_quats + 4 * i;
  T* os = v_scales + 3 * i;
  // Culled, or no gradient received: zeros, no recomputation (as the CPU kernel).
  if (radii[i] <= 0 || (vmx == T(0) && vmy == T(0) && vca == T(0) && vcb == T(0) &&
                        vcc == T(0) && vd == T(0))) {
    for (int k = 0; k < 3; ++k) om[k] = T(0);
    for (int k = 0; k < 4; ++k) oq[k] = T(0);
    for (int k = 0; k < 3; ++k) os[k] = T(0);
    return;
  }
  const auto g = math::load_gaussian<T>(means + 3 * i, quats + 4 * i, scales + 3 * i);
  const math::GaussianGrad<T> r = math::project_gaussian_vjp<T>(cam, g, vmx, vmy, vca, vcb,
                                                                vcc, vd);
  // 0 + x, as the CPU kernel: -0 becomes +0.
  om[0] = T(0) + r.mean.x;
  om[1] = T(0) + r.mean.y;
  om[2] = T(0) + r.mean.z;
  for (int k = 0; k < 4; ++k) oq[k] = T(0) + r.quat[k];
  for (int k = 0; k < 3; ++k) os[k] = T(0) + r.scale[k];
}

}  // namespace

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> project_cuda(
    const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
    const at::Tensor& viewmat, const at::Tensor& K, int64_t width, int64_t height,
    double near_plane) {
  TORCH_CHECK(means.is_cuda(), "means must be a CUDA tensor, got ", means.device());
  check_project_inputs(means, quats, scales, viewmat, K, width, height);
  const c10::cuda::CUDAGuard guard(means.device());
  const int64_t n = means.size(0);
  at::Tensor means2d = at::empty({n, 2}, means.options());
  at::Tensor conics = at::empty({n, 3}, means.options());
  at::Tensor depths = at::empty({n}, means.options());
  at::Tensor radii = at::empty({n}, means.options().dtype(at::kInt));
  if (n == 0) return {means2d, conics, depths, radii};
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "cobgs::project_cuda", [&] {
    project_kernel<scalar_t><<<cuda::blocks_for(n, kThreads), kThreads, 0, cuda::stream()>>>(
        n, viewmat.data_ptr<scalar_t>(), K.data_ptr<scalar_t>(), static_cast<int>(width),
        static_cast<int>(height), static_cast<scalar_t>(near_plane), means.data_ptr<scalar_t>(),
        quats.data_ptr<scalar_t>(), scales.data_ptr<scalar_t>(), means2d.data_ptr<scalar_t>(),
        conics.data_ptr<scalar_t>(), depths.data_ptr<scalar_t>(), radii.data_ptr<int32_t>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return {means2d, conics, depths, radii};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> project_bwd_cuda(
    const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
    const at::Tensor& viewmat, const at::Tensor& K, int64_t width, int64_t height,
    const at::Tensor& radii, const at::Tensor& v_means2d, const at::Tensor& v_conics,
    const at::Tensor& v_depths) {
  TORCH_CHECK(means.is_cuda(), "means must be a CUDA tensor, got ", means.device());
  check_project_inputs(means, quats, scales, viewmat, K, width, height);
  check_project_bwd_inputs(means, radii, v_means2d, v_conics, v_depths);
  const c10::cuda::CUDAGuard guard(means.device());
  const int64_t n = means.size(0);
  at::Tensor v_means = at::empty_like(means);
  at::Tensor v_quats = at::empty_like(quats);
  at::Tensor v_scales = at::empty_like(scales);
  if (n == 0) return {v_means, v_quats, v_scales};
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "cobgs::project_bwd_cuda", [&] {
    project_bwd_kernel<scalar_t>
        <<<cuda::blocks_for(n, kThreads), kThreads, 0, cuda::stream()>>>(
            n, viewmat.data_ptr<scalar_t>(), K.data_ptr<scalar_t>(), static_cast<int>(width),
            static_cast<int>(height), means.data_ptr<scalar_t>(), quats.data_ptr<scalar_t>(),
            scales.data_ptr<scalar_t>(), radii.data_ptr<int32_t>(),
            v_means2d.data_ptr<scalar_t>(), v_conics.data_ptr<scalar_t>(),
            v_depths.data_ptr<scalar_t>(), v_means.data_ptr<scalar_t>(),
            v_quats.data_ptr<scalar_t>(), v_scales.data_ptr<scalar_t>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return {v_means, v_quats, v_scales};
}

TORCH_LIBRARY_IMPL(cobgs, CUDA, m) {
  m.impl("project", &project_cuda);
  m.impl("project_bwd", &project_bwd_cuda);
}

}  // namespace cobgs
