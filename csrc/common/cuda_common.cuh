// Helpers shared by the CUDA kernels (*_cuda.cu): input checks, launch checks, grid sizes,
// the current stream, and warp reductions. Compiled only into builds with CUDA (see
// cobgs/_build.py); the math itself lives in gs_math.h / sh_math.h, shared with the CPU.
#pragma once

#include <ATen/cuda/CUDAContext.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <torch/types.h>

#include "checks.h"

// A contiguous CUDA tensor on the device of `ref` (the op's first tensor).
#define COBGS_CHECK_CUDA_INPUT(x, ref)                                                   \
  TORCH_CHECK((x).is_cuda() && (x).device() == (ref).device(), #x " must be a CUDA tensor " \
              "on ", (ref).device(), " (the device of the op's first tensor), got ",      \
              (x).device());                                                             \
  COBGS_CHECK_CONTIGUOUS(x)

namespace cobgs {
namespace cuda {

constexpr unsigned kFullMask = 0xffffffffu;

inline cudaStream_t stream() { return at::cuda::getCurrentCUDAStream(); }

inline unsigned int blocks_for(int64_t n, int threads) {
  return static_cast<unsigned int>((n + threads - 1) / threads);
}

// Sum over the 32 lanes of a warp; the result is valid in lane 0.
template <typename T>
__device__ __forceinline__ T warp_sum(T v) {
  for (int d = 16; d > 0; d >>= 1) v += __shfl_down_sync(kFullMask, v, d);
  return v;
}

// Max over the 32 lanes of a warp; the result is valid in every lane.
__device__ __forceinline__ int warp_max_all(int v) {
  for (int d = 16; d > 0; d >>= 1) v = max(v, __shfl_xor_sync(kFullMask, v, d));
  return v;
}

}  // namespace cuda
}  // namespace cobgs
