// Helpers shared by the CPU forward and backward blending kernels: input checks, the
// per-Gaussian data both passes precompute, and the loop over the pixels of a tile that
// a Gaussian can reach.
//
// Loop order: a tile is processed Gaussian by Gaussian (front to back in the forward,
// back to front in the backward), each updating the per-pixel state of the tile's 256
// pixels held in small structure-of-arrays buffers. That lets a Gaussian visit only the
// pixel rows/columns inside its α >= 1/255 ellipse, and lets the backward pass sum a
// Gaussian's gradient over the tile in registers and write it once, to a slot of its own
// (one slot per tile-list entry, reduced afterwards in a fixed order): no atomics, and
// the result does not depend on the thread schedule.
#pragma once

#include <torch/types.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <vector>

#include "../common/checks.h"
#include "../common/gs_math.h"
#include "../common/parallel_cpu.h"

namespace cobgs {
namespace blend_detail {

using math::kTileSize;

// Per-Gaussian data of both passes, compact so that a tile-list entry costs one cache
// line (entries of a tile point to Gaussians all over memory).
template <typename T>
struct GaussPrep {
  T mx, my, ca, cb, cc, o;
  T power_reject;          // power < this ⇒ α < 1/255 for sure (checked before exp)
  int32_t x0, x1, y0, y1;  // pixel box that can get α >= 1/255; empty if none can
};

// A per-thread buffer kept across calls (grow-only). Fresh multi-megabyte allocations
// are mmap'ed and zero-filled page by page by the kernel on every call, which cost
// several milliseconds per render; these buffers stay mapped. Contents are left as the
// previous call wrote them: callers initialise what they read. `Tag` tells the buffers
// of one thread apart.
template <typename V, int Tag>
V* reusable_buffer(size_t n) {
  thread_local std::vector<V> buf;
  if (buf.size() < n) buf.resize(n);
  return buf.data();
}

// Fills prep[0..n). Called inside the kernels' parallel region: the loop is an orphaned
// worksharing construct, so the threads split it without another fork/join.
template <typename T>
void prepare(const T* m2, const T* co, const T* op, int64_t n, GaussPrep<T>* prep) {
  const double eps = std::numeric_limits<T>::epsilon() * 0.5;
#pragma omp for schedule(static)
  for (int64_t i = 0; i < n; ++i) {
    GaussPrep<T>& g = prep[i];
    g.mx = m2[2 * i];
    g.my = m2[2 * i + 1];
    g.ca = co[3 * i];
    g.cb = co[3 * i + 1];
    g.cc = co[3 * i + 2];
    g.o = op[i];
    const math::BlendBound bb = math::make_blend_bound(g.mx, g.my, g.ca, g.cb, g.cc, g.o, eps);
    g.power_reject = static_cast<T>(bb.power_reject);
    g.x0 = bb.x0;
    g.x1 = bb.x1;
    g.y0 = bb.y0;
    g.y1 = bb.y1;
  }
}

// Software prefetch of a Gaussian a few entries ahead in the tile list: the hardware
// prefetcher cannot guess these scattered addresses.
#if defined(__GNUC__) || defined(__clang__)
#define COBGS_PREFETCH(ptr) __builtin_prefetch(ptr)
#else
#define COBGS_PREFETCH(ptr) ((void)0)
#endif
constexpr int kPrefetchAhead = 8;

// Lane masks as 32-bit integers (-1 / 0). GCC 12 does not vectorise row loops whose
// conditions are combined as `bool` (it sizes the vectors for 8-bit lanes); with int32
// masks and -fno-trapping-math it if-converts and vectorises them.
inline int32_t mask32(bool c) { return c ? int32_t(-1) : int32_t(0); }

// Sum of lanes [0, nx) (nx a multiple of 4) in a fixed order: four interleaved partial
// sums, then a pairwise combination. Short dependency chains, and the same result
// whatever the thread schedule or SIMD width.
template <typename T>
inline T lane_sum(const T* lanes, int nx) {
  T part[4] = {T(0), T(0), T(0), T(0)};
  for (int b = 0; b < nx; b += 4)
    for (int k = 0; k < 4; ++k) part[k] += lanes[b + k];
  return (part[0] + part[1]) + (part[2] + part[3]);
}

// Up to this many labels, the label statistics use vectorised per-lane sums.
constexpr int kLaneLabels = 4;

// Shapes, dtypes and the consistency of the tile lists shared by both passes.
inline void check_blend_inputs(const at::Tensor& means2d, const at::Tensor& conics,
                               const at::Tensor& opacities, const at::Tensor& features,
                               const at::Tensor& background, const at::Tensor& tile_offsets,
                               const at::Tensor& flat_ids, int64_t width, int64_t height) {
  COBGS_CHECK_INPUT(means2d);
  COBGS_CHECK_INPUT(conics);
  COBGS_CHECK_INPUT(opacities);
  COBGS_CHECK_INPUT(features);
  COBGS_CHECK_INPUT(background);
  COBGS_CHECK_INPUT(tile_offsets);
  COBGS_CHECK_INPUT(flat_ids);
  TORCH_CHECK(means2d.scalar_type() == at::kFloat || means2d.scalar_type() == at::kDouble,
              "means2d must be float32 or float64, got ", means2d.scalar_type());
  TORCH_CHECK(means2d.dim() == 2, "means2d must have shape [N, 2], got ", means2d.sizes());
  TORCH_CHECK(features.dim() == 2, "features must have shape [N, C], got ", features.sizes());
  const int64_t n = means2d.size(0), c = features.size(1);
  TORCH_CHECK(c >= 1, "features must have at least one channel, got ", features.sizes());
  COBGS_CHECK_SHAPE(means2d, n, 2);
  COBGS_CHECK_SHAPE(conics, n, 3);
  COBGS_CHECK_SHAPE(opacities, n);
  COBGS_CHECK_SHAPE(features, n, c);
  COBGS_CHECK_SHAPE(background, c);
  for (const auto* t : {&conics, &opacities, &features, &background})
    COBGS_CHECK_DTYPE((*t), means2d.scalar_type());
  TORCH_CHECK(width > 0 && height > 0, "width and height must be positive, got ", width,
              " x ", height);
  const int64_t tiles = ((width + kTileSize - 1) / kTileSize) *
                        ((height + kTileSize - 1) / kTileSize);
  COBGS_CHECK_DTYPE(tile_offsets, at::kLong);
  COBGS_CHECK_DTYPE(flat_ids, at::kInt);
  COBGS_CHECK_SHAPE(tile_offsets, tiles + 1);
  TORCH_CHECK(flat_ids.dim() == 1, "flat_ids must be 1-D, got ", flat_ids.sizes());
  const int64_t* off = tile_offsets.data_ptr<int64_t>();
  TORCH_CHECK(off[0] == 0 && off[tiles] == flat_ids.numel(),
              "tile_offsets must run from 0 to len(flat_ids) = ", flat_ids.numel(), ", got ",
              off[0], " .. ", off[tiles]);
  for (int64_t t = 0; t < tiles; ++t)
    TORCH_CHECK(off[t] <= off[t + 1], "tile_offsets must be non-decreasing (tile ", t, ")");
  const int32_t* ids = flat_ids.data_ptr<int32_t>();
  const int64_t m = flat_ids.numel();
  bool ok = true;
  for (int64_t k = 0; k < m; ++k) ok &= (ids[k] >= 0) & (ids[k] < n);
  TORCH_CHECK(ok, "flat_ids must index Gaussians 0..", n - 1);
}

}  // namespace blend_detail
}  // namespace cobgs
