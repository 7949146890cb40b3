// CUDA implementation of the `bin_tiles` op family (see bin_tiles.h).
//
// The lists are those of the CPU op, entry for entry. (1) Every Gaussian's tile rectangle
// (tile_rect.h, narrowed by its `prep` box for the tight lists; the records come from
// gauss_prep.h, the CPU's code) and its tile count, scanned in index order. (2) One entry
// per (tile, Gaussian) at the Gaussian's place in the scan. (3) A stable device radix sort
// (CUB) of the entries by tile, then depth: float32 keys are tile · 2^32 + the bit pattern
// of the depth (positive floats order as their bits), and since the entries enter in index
// order, equal depths keep index order, as the CPU's stable sorts. float64 depths do not
// fit beside the tile in 64 bits: the Gaussians are first stably sorted by depth, and the
// entry key holds the depth rank instead. (4) tile_offsets from the boundaries between
// the tiles' runs. The only host synchronisation reads the number of entries (and the
// first bad depth, if any).
#include <torch/library.h>

#include <cub/cub.cuh>

#include "../blend/gauss_prep.h"
#include "../common/cuda_common.cuh"
#include "bin_tiles.h"
#include "tile_rect.h"

namespace cobgs {
namespace {

using bin_detail::Rect;
using blend_detail::GaussPrep;

constexpr int kThreads = 256;

template <typename T>
__global__ void prepare_kernel(int64_t n, const T* __restrict__ m2, const T* __restrict__ co,
                               const T* __restrict__ op, GaussPrep<T>* __restrict__ prep) {
  const int64_t i = blockIdx.x * int64_t(kThreads) + threadIdx.x;
  if (i < n) blend_detail::prepare_one(m2, co, op, i, prep + i);
}

// Step 1: rectangle and tile count of every Gaussian, and (float64) the depth key of the
// ones that cover some tile (the others get the largest key: they sort last).
template <typename T, typename Key>
__global__ void rect_kernel(int64_t n, const T* __restrict__ m2,
                            const int32_t* __restrict__ radii, const T* __restrict__ depths,
                            int tiles_x, int tiles_y, const GaussPrep<T>* __restrict__ prep,
                            Rect* __restrict__ rects, int64_t* __restrict__ counts,
                            Key* __restrict__ keys, int32_t* __restrict__ order,
                            unsigned long long* __restrict__ first_bad) {
  const int64_t i = blockIdx.x * int64_t(kThreads) + threadIdx.x;
  if (i >= n) return;
  Rect rc{0, 0, 0, 0};
  int64_t count = 0;
  Key key = ~Key(0);
  if (radii[i] > 0) {
    rc = bin_detail::tile_rect<T>(m2[2 * i], m2[2 * i + 1], radii[i], tiles_x, tiles_y);
    if (prep) rc = bin_detail::narrow_to_box(rc, prep[i].x0, prep[i].x1, prep[i].y0, prep[i].y1);
    const T d = depths[i];
    if (!(d > T(0) && isfinite(d))) atomicMin(first_bad, static_cast<unsigned long long>(i));
    if (rc.x0 < rc.x1 && rc.y0 < rc.y1) {
      count = int64_t(rc.x1 - rc.x0) * (rc.y1 - rc.y0);
      key = bin_detail::depth_key(d);
    }
  }
  rects[i] = rc;
  counts[i] = count;
  if (keys) {
    keys[i] = key;
    order[i] = static_cast<int32_t>(i);
  }
}

// Step 2 (float32): the entries of Gaussian i at [ends[i] - count, ends[i]), keyed
// tile · 2^32 + depth bits.
__global__ void emit_depth_kernel(int64_t n, const Rect* __restrict__ rects,
                                  const int64_t* __restrict__ ends,
                                  const float* __restrict__ depths, int tiles_x,
                                  uint64_t* __restrict__ keys, int32_t* __restrict__ ids) {
  const int64_t i = blockIdx.x * int64_t(kThreads) + threadIdx.x;
  if (i >= n) return;
  int64_t pos = i > 0 ? ends[i - 1] : 0;
  if (pos == ends[i]) return;
  const Rect rc = rects[i];
  const uint64_t depth = bin_detail::depth_key(depths[i]);
  for (int ty = rc.y0; ty < rc.y1; ++ty)
    for (int tx = rc.x0; tx < rc.x1; ++tx, ++pos) {
      keys[pos] = (uint64_t(int64_t(ty) * tiles_x + tx) << 32) | depth;
      ids[pos] = static_cast<int32_t>(i);
    }
}

// Step 2 (float64): the entries of the Gaussian of depth rank k at [ends[k] - count,
// ends[k]), keyed tile · 2^32 + k.
__global__ void emit_kernel(int64_t n, const int32_t* __restrict__ order,
                            const Rect* __restrict__ rects, const int64_t* __restrict__ ends,
                            int tiles_x, uint64_t* __restrict__ keys,
                            int32_t* __restrict__ ids) {
  const int64_t k = blockIdx.x * int64_t(kThreads) + threadIdx.x;
  if (k >= n) return;
  const int32_t g = order[k];
  const Rect rc = rects[g];
  int64_t pos = k > 0 ? ends[k - 1] : 0;
  if (pos == ends[k]) return;
  for (int ty = rc.y0; ty < rc.y1; ++ty)
    for (int tx = rc.x0; tx < rc.x1; ++tx, ++pos) {
      keys[pos] = (uint64_t(int64_t(ty) * tiles_x + tx) << 32) | uint64_t(k);
      ids[pos] = g;
    }
}

// Step 4: off[t] = the first entry of tile t or after (entries sorted by tile).
__global__ void offsets_kernel(int64_t m, const uint64_t* __restrict__ keys, int64_t n_tiles,
                               int64_t* __restrict__ off) {
  const int64_t j = blockIdx.x * int64_t(kThreads) + threadIdx.x;
  if (j >= m) return;
  const int64_t t = int64_t(keys[j] >> 32);
  const int64_t prev = j > 0 ? int64_t(keys[j - 1] >> 32) : -1;
  for (int64_t u = prev + 1; u <= t; ++u) off[u] = j;
  if (j == m - 1)
    for (int64_t u = t + 1; u <= n_tiles; ++u) off[u] = m;
}

// Stable sort of (keys, values) pairs by the low `bits` bits of the keys, into the
// `*_out` tensors (CUB's LSD radix sort keeps equal keys in input order).
template <typename Key>
void radix_sort_pairs(const at::Tensor& keys_in, at::Tensor& keys_out, const at::Tensor& vals_in,
                      at::Tensor& vals_out, int bits) {
  const int64_t n = keys_in.numel();
  TORCH_CHECK(n < (int64_t(1) << 31), "too many entries to sort: ", n);
  const Key* kin = reinterpret_cast<const Key*>(keys_in.data_ptr());
  Key* kout = reinterpret_cast<Key*>(keys_out.data_ptr());
  const int32_t* vin = vals_in.data_ptr<int32_t>();
  int32_t* vout = vals_out.data_ptr<int32_t>();
  size_t bytes = 0;
  C10_CUDA_CHECK(cub::DeviceRadixSort::SortPairs(nullptr, bytes, kin, kout, vin, vout,
                                                 static_cast<int>(n), 0, bits, cuda::stream()));
  at::Tensor tmp = at::empty({static_cast<int64_t>(bytes)},
                             keys_in.options().dtype(at::kByte));
  C10_CUDA_CHECK(cub::DeviceRadixSort::SortPairs(tmp.data_ptr(), bytes, kin, kout, vin, vout,
                                                 static_cast<int>(n), 0, bits, cuda::stream()));
}

int bits_for(int64_t v) {  // bits needed for the values 0 .. v
  int b = 1;
  while (b < 63 && (int64_t(1) << b) <= v) ++b;
  return b;
}

template <typename T>
void bin_tiles_kernel(const at::Tensor& means2d, const at::Tensor& radii, const at::Tensor& depths,
                      int tiles_x, int tiles_y, const GaussPrep<T>* prep,
                      at::Tensor& tile_offsets, at::Tensor& flat_ids) {
  using Key = decltype(bin_detail::depth_key(T(0)));
  constexpr bool kDepthInKey = sizeof(Key) == 4;  // float32: one sort
  const at::ScalarType key_type = sizeof(Key) == 4 ? at::kInt : at::kLong;
  const int64_t n = means2d.size(0);
  const int64_t n_tiles = int64_t(tiles_x) * tiles_y;
  const auto opts = means2d.options();
  at::Tensor rects = at::empty({n, 4}, opts.dtype(at::kInt));
  at::Tensor counts = at::empty({n}, opts.dtype(at::kLong));
  at::Tensor keys = at::empty({kDepthInKey ? 0 : n}, opts.dtype(key_type));
  at::Tensor order = at::empty({kDepthInKey ? 0 : n}, opts.dtype(at::kInt));
  at::Tensor first_bad = at::full({1}, n, opts.dtype(at::kLong));
  const auto grid = cuda::blocks_for(n, kThreads);
  rect_kernel<T, Key><<<grid, kThreads, 0, cuda::stream()>>>(
      n, means2d.data_ptr<T>(), radii.data_ptr<int32_t>(), depths.data_ptr<T>(), tiles_x,
      tiles_y, prep, reinterpret_cast<Rect*>(rects.data_ptr<int32_t>()),
      counts.data_ptr<int64_t>(), kDepthInKey ? nullptr : reinterpret_cast<Key*>(keys.data_ptr()),
      kDepthInKey ? nullptr : order.data_ptr<int32_t>(),
      reinterpret_cast<unsigned long long*>(first_bad.data_ptr<int64_t>()));
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  at::Tensor order_sorted, ends;
  if (kDepthInKey) {
    ends = counts.cumsum(0);
  } else {
    at::Tensor keys_sorted = at::empty_like(keys);
    order_sorted = at::empty_like(order);
    radix_sort_pairs<Key>(keys, keys_sorted, order, order_sorted, int(8 * sizeof(Key)));
    ends = counts.index_select(0, order_sorted).cumsum(0);
  }
  // One copy to the host: the first Gaussian with a bad depth and the number of entries.
  const at::Tensor head = at::cat({first_bad, ends.slice(0, n - 1, n)}).cpu();
  const int64_t bad = head.data_ptr<int64_t>()[0];
  const int64_t m = head.data_ptr<int64_t>()[1];
  if (bad < n) {
    const double d = depths.slice(0, bad, bad + 1).item<double>();
    TORCH_CHECK(false, "depths[", bad, "] of a visible Gaussian must be positive and finite, got ",
                d);
  }
  flat_ids = at::empty({m}, opts.dtype(at::kInt));
  if (m == 0) return;
  at::Tensor entry_keys = at::empty({m}, opts.dtype(at::kLong));
  at::Tensor entry_ids = at::empty({m}, opts.dtype(at::kInt));
  uint64_t* ekeys = reinterpret_cast<uint64_t*>(entry_keys.data_ptr<int64_t>());
  const Rect* rect_ptr = reinterpret_cast<const Rect*>(rects.data_ptr<int32_t>());
  if constexpr (kDepthInKey) {
    emit_depth_kernel<<<grid, kThreads, 0, cuda::stream()>>>(
        n, rect_ptr, ends.data_ptr<int64_t>(), depths.data_ptr<float>(), tiles_x, ekeys,
        entry_ids.data_ptr<int32_t>());
  } else {
    emit_kernel<<<grid, kThreads, 0, cuda::stream()>>>(
        n, order_sorted.data_ptr<int32_t>(), rect_ptr, ends.data_ptr<int64_t>(), tiles_x, ekeys,
        entry_ids.data_ptr<int32_t>());
  }
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  at::Tensor keys_out = at::empty_like(entry_keys);
  radix_sort_pairs<uint64_t>(entry_keys, keys_out, entry_ids, flat_ids, 32 + bits_for(n_tiles));
  offsets_kernel<<<cuda::blocks_for(m, kThreads), kThreads, 0, cuda::stream()>>>(
      m, reinterpret_cast<const uint64_t*>(keys_out.data_ptr<int64_t>()), n_tiles,
      tile_offsets.data_ptr<int64_t>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
}

int tiles_along(int64_t pixels) {
  return static_cast<int>((pixels + math::kTileSize - 1) / math::kTileSize);
}

}  // namespace

std::tuple<at::Tensor, at::Tensor> bin_tiles_cuda(const at::Tensor& means2d,
                                                  const at::Tensor& radii,
                                                  const at::Tensor& depths, int64_t width,
                                                  int64_t height) {
  TORCH_CHECK(means2d.is_cuda(), "means2d must be a CUDA tensor, got ", means2d.device());
  check_bin_inputs(means2d, radii, depths, width, height);
  const c10::cuda::CUDAGuard guard(means2d.device());
  const int tiles_x = tiles_along(width), tiles_y = tiles_along(height);
  at::Tensor tile_offsets =
      at::zeros({int64_t(tiles_x) * tiles_y + 1}, means2d.options().dtype(at::kLong));
  at::Tensor flat_ids = at::empty({0}, means2d.options().dtype(at::kInt));
  if (means2d.size(0) == 0) return {tile_offsets, flat_ids};
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "cobgs::bin_tiles_cuda", [&] {
    bin_tiles_kernel<scalar_t>(means2d, radii, depths, tiles_x, tiles_y, nullptr, tile_offsets,
                               flat_ids);
  });
  return {tile_offsets, flat_ids};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> bin_tiles_tight_cuda(
    const at::Tensor& means2d, const at::Tensor& radii, const at::Tensor& depths,
    const at::Tensor& conics, const at::Tensor& opacities, int64_t width, int64_t height) {
  TORCH_CHECK(means2d.is_cuda(), "means2d must be a CUDA tensor, got ", means2d.device());
  const int64_t n = check_bin_tight_inputs(means2d, radii, depths, conics, opacities, width,
                                           height);
  const c10::cuda::CUDAGuard guard(means2d.device());
  const int tiles_x = tiles_along(width), tiles_y = tiles_along(height);
  at::Tensor tile_offsets =
      at::zeros({int64_t(tiles_x) * tiles_y + 1}, means2d.options().dtype(at::kLong));
  at::Tensor flat_ids = at::empty({0}, means2d.options().dtype(at::kInt));
  at::Tensor prep;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "cobgs::bin_tiles_tight_cuda", [&] {
    using Prep = GaussPrep<scalar_t>;
    prep = at::empty({n, static_cast<int64_t>(sizeof(Prep))}, means2d.options().dtype(at::kByte));
    if (n == 0) return;
    Prep* records = reinterpret_cast<Prep*>(prep.data_ptr<uint8_t>());
    prepare_kernel<scalar_t><<<cuda::blocks_for(n, kThreads), kThreads, 0, cuda::stream()>>>(
        n, means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(),
        opacities.data_ptr<scalar_t>(), records);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
    bin_tiles_kernel<scalar_t>(means2d, radii, depths, tiles_x, tiles_y, records, tile_offsets,
                               flat_ids);
  });
  return {tile_offsets, flat_ids, prep};
}

namespace blend_detail {
// The records of every Gaussian into `prep` (blend and blend_bwd without given records).
template <typename T>
void prepare_cuda(const T* m2, const T* co, const T* op, int64_t n, GaussPrep<T>* prep) {
  if (n == 0) return;
  prepare_kernel<T><<<cuda::blocks_for(n, kThreads), kThreads, 0, cuda::stream()>>>(n, m2, co,
                                                                                       op, prep);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
}
template void prepare_cuda<float>(const float*, const float*, const float*, int64_t,
                                  GaussPrep<float>*);
template void prepare_cuda<double>(const double*, const double*, const double*, int64_t,
                                   GaussPrep<double>*);
}  // namespace blend_detail

TORCH_LIBRARY_IMPL(cobgs, CUDA, m) {
  m.impl("bin_tiles", &bin_tiles_cuda);
  m.impl("bin_tiles_tight", &bin_tiles_tight_cuda);
}

}  // namespace cobgs
