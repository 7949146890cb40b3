// CPU implementation of `bin_tiles` (see bin_tiles.h).
//
// Gaussians are first put in global depth order with a stable LSD radix sort on the
// bit patterns of their (positive) depths, then appended tile by tile in that order
// (a counting sort by tile, which is stable too), so each tile's run comes out sorted
// by depth with ties broken by index — the order the reference gets from stable sorts.
#include "bin_tiles.h"

#include <torch/library.h>

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <vector>

#include "../blend/blend_tile_cpu.h"
#include "../common/checks.h"
#include "../common/gs_math.h"
#include "../common/parallel_cpu.h"
#include "../common/prof_cpu.h"
#include "tile_rect.h"

namespace cobgs {
namespace {

using bin_detail::depth_key;
using bin_detail::narrow_to_box;
using bin_detail::Rect;
using bin_detail::tile_rect;

// A vector of the calling thread kept across calls (cleared, capacity kept): fresh
// multi-megabyte allocations are zero-filled page by page by the kernel on every call.
// `Tag` tells the buffers apart.
template <typename V, int Tag>
std::vector<V>& scratch() {
  thread_local std::vector<V> buf;
  return buf;
}

// Stable LSD radix sort of `ids` by `keys` (parallel arrays), 8 bits per pass, on all
// threads: per pass, every thread counts the digits of its contiguous chunk, works out
// where its chunk's entries of each digit go (after all smaller digits, and after the
// same digit of the chunks before its own), and scatters them. A stable sort has one
// result, so the order does not depend on the thread count. Passes whose digit is the
// same for every key are skipped.
template <typename K>
void radix_sort(std::vector<K>& keys, std::vector<int32_t>& ids) {
  const int64_t n = static_cast<int64_t>(keys.size());
  if (n == 0) return;
  std::vector<K>& k2 = scratch<K, 1>();
  std::vector<int32_t>& i2 = scratch<int32_t, 2>();
  k2.resize(n);
  i2.resize(n);
  constexpr int kPasses = static_cast<int>(sizeof(K));
  const int nt = range_threads(n, 4096);
  std::vector<int64_t>& hist = scratch<int64_t, 7>();  // [nt][256] per pass
  hist.assign(size_t(nt) * 256, 0);
  int swaps = 0;  // passes that moved the data (the same count on every thread)
#pragma omp parallel num_threads(nt)
  {
    const int tid = omp_get_thread_num();
    const auto [i0, i1] = thread_range(n, tid, nt);
    K* src_k = keys.data();
    K* dst_k = k2.data();
    int32_t* src_i = ids.data();
    int32_t* dst_i = i2.data();
    int64_t* my = hist.data() + size_t(tid) * 256;
    for (int pass = 0; pass < kPasses; ++pass) {
      const int shift = 8 * pass;
      std::fill(my, my + 256, int64_t(0));
      for (int64_t i = i0; i < i1; ++i) ++my[(src_k[i] >> shift) & 0xFF];
#pragma omp barrier
      int64_t where[256];
      int64_t run = 0;
      bool all_one_digit = false;
      for (int b = 0; b < 256; ++b) {
        int64_t before = 0, total = 0;
        for (int t = 0; t < nt; ++t) {
          const int64_t c = hist[size_t(t) * 256 + b];
          if (t < tid) before += c;
          total += c;
        }
        all_one_digit |= total == n;
        where[b] = run + before;
        run += total;
      }
      if (!all_one_digit) {
        for (int64_t i = i0; i < i1; ++i) {
          const int64_t dst = where[(src_k[i] >> shift) & 0xFF]++;
          dst_k[dst] = src_k[i];
          dst_i[dst] = src_i[i];
        }
        std::swap(src_k, dst_k);
        std::swap(src_i, dst_i);
      }
      // Everyone has read the counts and written its entries before the next pass.
#pragma omp barrier
      if (!all_one_digit && tid == 0) ++swaps;
    }
  }
  if (swaps % 2 == 1) {
    keys.swap(k2);
    ids.swap(i2);
  }
}

template <typename T>
void bin_tiles_kernel(const at::Tensor& means2d, const at::Tensor& radii,
                      const at::Tensor& depths, int tiles_x, int tiles_y,
                      const blend_detail::GaussPrep<T>* prep, at::Tensor& tile_offsets,
                      at::Tensor& flat_ids) {
  const int64_t n = means2d.size(0);
  const int64_t n_tiles = int64_t(tiles_x) * tiles_y;
  using Key = decltype(depth_key(T(0)));
  const T* m2 = means2d.data_ptr<T>();
  const T* d = depths.data_ptr<T>();
  const int32_t* r = radii.data_ptr<int32_t>();

  COBGS_PROF_COUNT(kCallsBin, 1);
  std::vector<Key>& keys = scratch<Key, 0>();
  std::vector<int32_t>& order = scratch<int32_t, 3>();
  // Every Gaussian's tile rectangle, and the Gaussians that cover some tile (they enter
  // the depth sort) in index order: each thread takes a contiguous range, counts, and
  // after a barrier writes its range's keys after those of the ranges before it.
  std::vector<Rect>& rect_of = scratch<Rect, 6>();
  rect_of.resize(n);
  keys.resize(n);
  order.resize(n);
  const int nt = range_threads(n, 4096);
  std::vector<int64_t> kept(size_t(nt) + 1, 0);
  std::vector<int64_t> first_bad(size_t(nt), -1);  // a visible Gaussian with a bad depth
#ifdef COBGS_PROFILE
  auto* sort_scope = new prof::Scope(prof::kBinSort);
#endif
#pragma omp parallel num_threads(nt)
  {
    const int tid = omp_get_thread_num();
    const auto [i0, i1] = thread_range(n, tid, nt);
    int64_t count = 0;
    for (int64_t i = i0; i < i1; ++i) {
      Rect rc{0, 0, 0, 0};
      if (r[i] > 0) {
        rc = tile_rect<T>(m2[2 * i], m2[2 * i + 1], r[i], tiles_x, tiles_y);
        if (prep) rc = narrow_to_box(rc, prep[i].x0, prep[i].x1, prep[i].y0, prep[i].y1);
        if (!(d[i] > T(0) && std::isfinite(d[i])) && first_bad[tid] < 0) first_bad[tid] = i;
        count += rc.x0 < rc.x1 && rc.y0 < rc.y1;
      }
      rect_of[i] = rc;
    }
    kept[size_t(tid) + 1] = count;
#pragma omp barrier
    int64_t pos = 0;
    for (int t = 0; t <= tid; ++t) pos += kept[size_t(t)];
    for (int64_t i = i0; i < i1; ++i) {
      const Rect& rc = rect_of[i];
      if (r[i] <= 0 || rc.x0 >= rc.x1 || rc.y0 >= rc.y1) continue;
      keys[pos] = depth_key(d[i]);
      order[pos] = static_cast<int32_t>(i);
      ++pos;
    }
  }
  for (const int64_t i : first_bad)
    TORCH_CHECK(i < 0, "depths[", i, "] of a visible Gaussian must be positive and finite, got ",
                d[i]);
  int64_t total = 0;
  for (const int64_t c : kept) total += c;
  keys.resize(total);
  order.resize(total);
  radix_sort(keys, order);
#ifdef COBGS_PROFILE
  delete sort_scope;
#endif
  COBGS_PROF_SCOPE(kBinLists);  // (the master thread only)

  const int64_t nv = static_cast<int64_t>(order.size());
  std::vector<Rect>& rects = scratch<Rect, 4>();
  rects.resize(nv);
  // Two fixed halves of the depth order are counted and placed in parallel; a tile's
  // entries from the first half precede those from the second, so the lists are the same
  // as a serial pass whatever the thread count.
  const int64_t half = nv / 2;
  std::vector<int64_t>& cnt = scratch<int64_t, 5>();  // [2][n_tiles]: counts, then cursors
  cnt.assign(2 * size_t(n_tiles), 0);
  int64_t* off = tile_offsets.data_ptr<int64_t>();
#pragma omp parallel num_threads(cpu_threads())
  {
#pragma omp for schedule(static)
    for (int64_t k = 0; k < nv; ++k) rects[k] = rect_of[order[k]];
#pragma omp for schedule(static)
    for (int h = 0; h < 2; ++h) {
      int64_t* c = cnt.data() + h * n_tiles;
      for (int64_t k = h == 0 ? 0 : half; k < (h == 0 ? half : nv); ++k) {
        const Rect& rc = rects[k];
        for (int ty = rc.y0; ty < rc.y1; ++ty)
          for (int tx = rc.x0; tx < rc.x1; ++tx) ++c[int64_t(ty) * tiles_x + tx];
      }
    }
  }
  int64_t* c0 = cnt.data();
  int64_t* c1 = cnt.data() + n_tiles;
  for (int64_t t = 0; t < n_tiles; ++t) {
    const int64_t a = c0[t], b = c1[t];
    c0[t] = off[t];      // cursor of the first half
    c1[t] = off[t] + a;  // cursor of the second half
    off[t + 1] = off[t] + a + b;
  }
  flat_ids = at::empty({off[n_tiles]}, means2d.options().dtype(at::kInt));
  int32_t* ids = flat_ids.data_ptr<int32_t>();
#pragma omp parallel for schedule(static) num_threads(cpu_threads())
  for (int h = 0; h < 2; ++h) {
    int64_t* cursor = cnt.data() + h * n_tiles;
    for (int64_t k = h == 0 ? 0 : half; k < (h == 0 ? half : nv); ++k) {
      const Rect& rc = rects[k];
      for (int ty = rc.y0; ty < rc.y1; ++ty)
        for (int tx = rc.x0; tx < rc.x1; ++tx) ids[cursor[int64_t(ty) * tiles_x + tx]++] = order[k];
    }
  }
}

// blend's per-Gaussian records of all n Gaussians, in parallel.
template <typename T>
void prepare_all(const T* m2, const T* co, const T* op, int64_t n,
                 blend_detail::GaussPrep<T>* records) {
#pragma omp parallel num_threads(cpu_threads())
  {
    COBGS_PROF_SCOPE(kBinPrepare);
    blend_detail::prepare<T>(m2, co, op, n, records);
  }
}

}  // namespace

std::tuple<at::Tensor, at::Tensor> bin_tiles_cpu(const at::Tensor& means2d,
                                                 const at::Tensor& radii,
                                                 const at::Tensor& depths, int64_t width,
                                                 int64_t height) {
  COBGS_CHECK_CPU(means2d);
  check_bin_inputs(means2d, radii, depths, width, height);
  const int tiles_x = static_cast<int>((width + math::kTileSize - 1) / math::kTileSize);
  const int tiles_y = static_cast<int>((height + math::kTileSize - 1) / math::kTileSize);
  const int64_t n_tiles = int64_t(tiles_x) * tiles_y;
  at::Tensor tile_offsets = at::zeros({n_tiles + 1}, means2d.options().dtype(at::kLong));
  at::Tensor flat_ids;

  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "cobgs::bin_tiles", [&] {
    bin_tiles_kernel<scalar_t>(means2d, radii, depths, tiles_x, tiles_y, nullptr,
                               tile_offsets, flat_ids);
  });
  return {tile_offsets, flat_ids};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> bin_tiles_tight_cpu(
    const at::Tensor& means2d, const at::Tensor& radii, const at::Tensor& depths,
    const at::Tensor& conics, const at::Tensor& opacities, int64_t width, int64_t height) {
  COBGS_CHECK_CPU(means2d);
  const int64_t n = check_bin_tight_inputs(means2d, radii, depths, conics, opacities, width,
                                           height);
  const int tiles_x = static_cast<int>((width + math::kTileSize - 1) / math::kTileSize);
  const int tiles_y = static_cast<int>((height + math::kTileSize - 1) / math::kTileSize);
  const int64_t n_tiles = int64_t(tiles_x) * tiles_y;
  at::Tensor tile_offsets = at::zeros({n_tiles + 1}, means2d.options().dtype(at::kLong));
  at::Tensor flat_ids;
  at::Tensor prep;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "cobgs::bin_tiles_tight", [&] {
    using Prep = blend_detail::GaussPrep<scalar_t>;
    prep = at::empty({n, static_cast<int64_t>(sizeof(Prep))}, means2d.options().dtype(at::kByte));
    TORCH_CHECK(reinterpret_cast<uintptr_t>(prep.data_ptr()) % alignof(Prep) == 0,
                "the allocator returned memory aligned below ", alignof(Prep), " bytes");
    Prep* records = reinterpret_cast<Prep*>(prep.data_ptr<uint8_t>());
    // (No pragma here: directives inside the dispatch macro's argument are not honoured.)
    prepare_all<scalar_t>(means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(),
                          opacities.data_ptr<scalar_t>(), n, records);
    bin_tiles_kernel<scalar_t>(means2d, radii, depths, tiles_x, tiles_y, records,
                               tile_offsets, flat_ids);
  });
  return {tile_offsets, flat_ids, prep};
}

TORCH_LIBRARY_IMPL(cobgs, CPU, m) {
  m.impl("bin_tiles", &bin_tiles_cpu);
  m.impl("bin_tiles_tight", &bin_tiles_tight_cpu);
}

}  // namespace cobgs
