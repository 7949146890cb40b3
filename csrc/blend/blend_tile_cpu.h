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
#include <cstddef>
#include <cstring>
#include <limits>
#include <optional>
#include <vector>

#include "../common/checks.h"
#include "../common/gs_math.h"
#include "../common/parallel_cpu.h"
#include "../common/prof_cpu.h"
#include "../common/simd_cpu.h"
#include "gauss_prep.h"
#include "given_prep.h"

namespace cobgs {
namespace blend_detail {

using math::kTileSize;

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

// Fills prep[i0..i1) (csrc/blend/prepare_lanes_cpu.h); the version for this CPU's
// instruction set.
template <typename T>
using PrepareRangeFn = void (*)(const T* m2, const T* co, const T* op, int64_t i0, int64_t i1,
                                GaussPrep<T>* prep);
template <typename T>
PrepareRangeFn<T> prepare_range_fn();

// Fills prep[0..n). Called inside the kernels' parallel region: the loop is an orphaned
// worksharing construct, so the threads split it without another fork/join. Chunks of
// whole lane blocks, split statically: the records do not depend on the thread count.
template <typename T>
void prepare(const T* m2, const T* co, const T* op, int64_t n, GaussPrep<T>* prep) {
  const PrepareRangeFn<T> fn = prepare_range_fn<T>();
  constexpr int64_t kChunk = 256;
  const int64_t chunks = (n + kChunk - 1) / kChunk;
#pragma omp for schedule(static)
  for (int64_t c = 0; c < chunks; ++c)
    fn(m2, co, op, c * kChunk, std::min(n, (c + 1) * kChunk), prep);
}

// Software prefetch of a Gaussian a few entries ahead in the tile list: the hardware
// prefetcher cannot guess these scattered addresses.
#if defined(__GNUC__) || defined(__clang__)
#define COBGS_PREFETCH(ptr) __builtin_prefetch(ptr)
#define COBGS_PREFETCH_W(ptr) __builtin_prefetch(ptr, 1)  // for writing
#else
#define COBGS_PREFETCH(ptr) ((void)0)
#define COBGS_PREFETCH_W(ptr) ((void)0)
#endif
constexpr int kPrefetchAhead = 8;

// Tile-list entries grouped by Gaussian: a stable counting sort of flat_ids. Per-entry
// results (gradients, label statistics) are written to slot[j] instead of j, so that each
// Gaussian's entries lie contiguously, in list order, in slots start[g] .. start[g + 1].
// The per-Gaussian reduction then runs in parallel over Gaussians, streams its input, and
// sums every Gaussian's entries in ascending list order whatever the thread count.
struct EntrySlots {
  int64_t* start;  // [n + 1]
  int64_t* slot;   // [m]
  int64_t* count;  // [2 n] scratch
  // Buffers of the calling thread (call outside the parallel region).
  static EntrySlots buffers(int64_t m, int64_t n) {
    return {reusable_buffer<int64_t, 10>(size_t(n) + 1), reusable_buffer<int64_t, 11>(size_t(m)),
            reusable_buffer<int64_t, 12>(2 * size_t(n))};
  }
};

// The middle step of the two-halves grouping below: from the per-half counts of every
// Gaussian (e.count, two rows of n), its first slot (e.start) and each half's cursor
// (written back into e.count). One thread does it; the others wait at the barrier.
inline void place_two_halves(int64_t n, const EntrySlots& e) {
#pragma omp single
  {
    int64_t run = 0;
    int64_t* c0 = e.count;
    int64_t* c1 = e.count + n;
    for (int64_t g = 0; g < n; ++g) {
      const int64_t a = c0[g], b = c1[g];
      e.start[g] = run;
      c0[g] = run;      // cursor of the first half
      c1[g] = run + a;  // cursor of the second half
      run += a + b;
    }
    e.start[n] = run;
  }  // implicit barrier
}

// Fills the grouping of `ids` [m] (values in 0..n-1). Called inside a parallel region by
// every thread (orphaned worksharing; ends with a barrier). Two fixed halves of the list
// are counted and placed in parallel; the slots do not depend on the thread count.
inline void group_entries(const int32_t* ids, int64_t m, int64_t n, const EntrySlots& e) {
  const int64_t half = m / 2;
#pragma omp for schedule(static)
  for (int h = 0; h < 2; ++h) {
    int64_t* c = e.count + h * n;
    std::fill(c, c + n, int64_t(0));
    const int64_t lo = h == 0 ? 0 : half, hi = h == 0 ? half : m;
    for (int64_t j = lo; j < hi; ++j) ++c[ids[j]];
  }
  place_two_halves(n, e);
#pragma omp for schedule(static)
  for (int h = 0; h < 2; ++h) {
    int64_t* cur = e.count + h * n;
    const int64_t lo = h == 0 ? 0 : half, hi = h == 0 ? half : m;
    for (int64_t j = lo; j < hi; ++j) e.slot[j] = cur[ids[j]]++;
  }
}

// As group_entries, for the entries the backward pass visits only: in tile t, the first
// live[t] entries of its list (those in front of some pixel's last contributor). The
// other entries get no slot (slot[j] is left unset and must not be read). On scenes
// where pixels become opaque early most of the list is behind them, and grouping and
// reducing only the live entries saves most of that work. Deterministic as
// group_entries: two fixed halves of the tiles, in list order.
inline void group_live_entries(const int32_t* ids, const int64_t* off, int64_t n_tiles,
                               const int32_t* live, int64_t n, const EntrySlots& e) {
  const int64_t half = n_tiles / 2;
#pragma omp for schedule(static)
  for (int h = 0; h < 2; ++h) {
    int64_t* c = e.count + h * n;
    std::fill(c, c + n, int64_t(0));
    const int64_t t0 = h == 0 ? 0 : half, t1 = h == 0 ? half : n_tiles;
    for (int64_t t = t0; t < t1; ++t)
      for (int64_t j = off[t]; j < off[t] + live[t]; ++j) ++c[ids[j]];
  }
  place_two_halves(n, e);
#pragma omp for schedule(static)
  for (int h = 0; h < 2; ++h) {
    int64_t* cur = e.count + h * n;
    const int64_t t0 = h == 0 ? 0 : half, t1 = h == 0 ? half : n_tiles;
    for (int64_t t = t0; t < t1; ++t)
      for (int64_t j = off[t]; j < off[t] + live[t]; ++j) e.slot[j] = cur[ids[j]]++;
  }
}

// Tiles in decreasing order of list length (ties: tile index), the order the dynamic
// schedule hands them out: the long tiles start first, so no thread is left with one
// long tile at the end while the other idles. Results do not depend on the order.
inline const int64_t* tile_order(const int64_t* off, int64_t n_tiles) {
  int64_t* order = reusable_buffer<int64_t, 14>(size_t(n_tiles));
  for (int64_t t = 0; t < n_tiles; ++t) order[t] = t;
  std::stable_sort(order, order + n_tiles, [off](int64_t a, int64_t b) {
    return off[a + 1] - off[a] > off[b + 1] - off[b];
  });
  return order;
}

// The consistency of the tile lists (on the host; the shapes were checked by
// check_blend_inputs, blend.h).
inline void check_tile_lists_cpu(const at::Tensor& tile_offsets, const at::Tensor& flat_ids,
                                 int64_t n) {
  const int64_t tiles = tile_offsets.numel() - 1;
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
