// What the CUDA forward and backward blending passes share (blend_fwd_cuda.cu,
// blend_bwd_cuda.cu): one 16x16-thread block per tile, one thread per pixel; the tile's
// list is walked in batches staged in shared memory (the records of gauss_prep.h and the
// features of up to kSharedChannels channels); the per-Gaussian records, given or
// computed; and the input checks, made where the values are read.
#pragma once

#include "../common/cuda_common.cuh"
#include "../common/gs_math.h"
#include "blend.h"
#include "gauss_prep.h"
#include "given_prep.h"

namespace cobgs {
namespace blend_detail {

constexpr int kBlock = math::kTilePixels;  // threads per block = pixels per tile
constexpr int kSharedChannels = 4;          // up to this many channels: kernels with NC fixed

// Fills prep[0..n) (csrc/bin_tiles/bin_tiles_cuda.cu).
template <typename T>
void prepare_cuda(const T* m2, const T* co, const T* op, int64_t n, GaussPrep<T>* prep);

// The records the passes read: the given ones (checked), or fresh ones in `storage`.
template <typename T>
const GaussPrep<T>* prep_for_pass(const std::optional<at::Tensor>& prep,
                                  const at::Tensor& means2d, const at::Tensor& conics,
                                  const at::Tensor& opacities, at::Tensor& storage) {
  if (const GaussPrep<T>* given = given_prep<T>(prep, means2d)) return given;
  const int64_t n = means2d.size(0);
  storage = at::empty({n, static_cast<int64_t>(sizeof(GaussPrep<T>))},
                      means2d.options().dtype(at::kByte));
  GaussPrep<T>* records = reinterpret_cast<GaussPrep<T>*>(storage.data_ptr<uint8_t>());
  prepare_cuda<T>(means2d.data_ptr<T>(), conics.data_ptr<T>(), opacities.data_ptr<T>(), n,
                  records);
  return records;
}

// What the kernels found wrong in their inputs (bits of one int on the device, read once
// after the kernel): the lists and labels may come from a caller rather than from
// bin_tiles, so every offset, id, label and n_contrib is checked where it is read, and a
// bad one is skipped (never dereferenced) and reported.
enum InputErrors : int { kBadOffsets = 1, kBadIds = 2, kBadLabels = 4, kBadNContrib = 8 };

// The tile's list [lo, hi), or an empty one (and kBadOffsets) when tile_offsets does not
// run from 0 to m without decreasing there.
__device__ __forceinline__ void tile_list(const int64_t* off, int64_t tile, int64_t n_tiles,
                                          int64_t m, int* error, int64_t& lo, int64_t& hi) {
  lo = off[tile];
  hi = off[tile + 1];
  const bool bad = lo < 0 || hi < lo || hi > m || (tile == 0 && lo != 0) ||
                   (tile == n_tiles - 1 && hi != m);
  if (bad) {
    if (threadIdx.x == 0) atomicOr(error, kBadOffsets);
    lo = hi = 0;
  }
}

// Entry j's Gaussian and record; an id outside 0..n-1 gets an empty record (its box holds
// no pixel) and reports kBadIds. Returns the id, or -1.
template <typename T>
__device__ __forceinline__ int32_t load_entry(const int32_t* ids, int64_t j, int64_t n,
                                              const GaussPrep<T>* prep, GaussPrep<T>& rec,
                                              int* error) {
  const int32_t g = ids[j];
  if (g < 0 || g >= n) {
    atomicOr(error, kBadIds);
    rec = GaussPrep<T>{};  // x0 = x1 = 0: an empty box
    return -1;
  }
  rec = prep[g];
  return g;
}

// Raises the errors a kernel reported (one copy to the host; the ops skip it when called
// with check=False).
inline void raise_input_errors(const at::Tensor& error, int64_t n, int64_t num_labels) {
  const int e = error.item<int>();
  TORCH_CHECK(!(e & kBadOffsets), "tile_offsets must run from 0 to len(flat_ids) without "
              "decreasing (the tile_offsets output of bin_tiles)");
  TORCH_CHECK(!(e & kBadIds), "flat_ids must index Gaussians 0..", n - 1);
  TORCH_CHECK(!(e & kBadLabels), "pixel_labels must lie in -1..", num_labels - 1);
  TORCH_CHECK(!(e & kBadNContrib), "n_contrib must lie in 0 .. the length of the pixel's tile "
              "list (the n_contrib output of the forward pass with the same tile lists)");
}

// The pixel of this thread in tile `tile`.
struct TilePixel {
  int x, y;
  bool inside;
  int64_t index;  // y * width + x
};

__device__ __forceinline__ TilePixel tile_pixel(int64_t tile, int tiles_x, int width,
                                                int height) {
  TilePixel p;
  p.x = int(tile % tiles_x) * math::kTileSize + int(threadIdx.x) % math::kTileSize;
  p.y = int(tile / tiles_x) * math::kTileSize + int(threadIdx.x) / math::kTileSize;
  p.inside = p.x < width && p.y < height;
  p.index = int64_t(p.y) * width + p.x;
  return p;
}

// The Gaussian's exponent at the pixel centre, in the CPU kernels' operation order
// (blend_block_cpu.h): power = -0.5 (a dx² + c dy²) - b dx dy.
template <typename T>
__device__ __forceinline__ T pixel_power(const GaussPrep<T>& g, T dx, T dy) {
  return T(-0.5) * (g.ca * dx * dx + g.cc * dy * dy) - g.cb * dx * dy;
}

// Whether the pixel lies in the record's box (outside it no α reaches 1/255).
template <typename T>
__device__ __forceinline__ bool in_box(const GaussPrep<T>& g, int x, int y) {
  return x >= g.x0 && x < g.x1 && y >= g.y0 && y < g.y1;
}

// -- the fast path (the default; COBGS_CUDA_EXACT=1 or cobgs::set_cuda_fast(False) selects the
// exact one). Verified on an H100 by tests/render/test_cuda.py's tolerance tests and
// make gpu-check (docs/benchmarks/cuda_h100.md) --------------------------------------------
// The exact path makes every per-pixel decision with the CPU kernels' roundings (no fused
// multiply-adds, the shared polynomial exp). The fast path evaluates the exponent with fused
// multiply-adds and the hardware exp (__expf: 2 ulp), and accumulates colours with fused
// multiply-adds: images and gradients then agree with the CPU op within rounding, and a
// pixel's decisions (blended or not, clamped or not, stopped or not) can differ where α lies
// within a few 1e-7 (relative) of 1/255 or 0.99, or T of 1e-4. Forward and backward use the
// same formulas, so they agree with each other exactly.
template <typename T>
__device__ __forceinline__ T fast_exp(T x);
template <>
__device__ __forceinline__ float fast_exp<float>(float x) { return __expf(x); }
template <>
__device__ __forceinline__ double fast_exp<double>(double x) { return exp(x); }

template <typename T>
__device__ __forceinline__ T fast_power(const GaussPrep<T>& g, T dx, T dy) {
  return fma(T(-0.5) * g.ca, dx * dx, fma(T(-0.5) * g.cc, dy * dy, -g.cb * dx * dy));
}

// The exponent and exp of a path: kFast picks the fast formulas.
template <bool kFast, typename T>
__device__ __forceinline__ T path_power(const GaussPrep<T>& g, T dx, T dy) {
  return kFast ? fast_power(g, dx, dy) : pixel_power(g, dx, dy);
}
template <bool kFast, typename T>
__device__ __forceinline__ T path_exp(T x) {
  return kFast ? fast_exp(x) : math::gauss_exp(x);
}

}  // namespace blend_detail

// Whether the CUDA blending passes take the fast path (csrc/blend/fast_path.cpp).
bool cuda_fast_path();

}  // namespace cobgs
