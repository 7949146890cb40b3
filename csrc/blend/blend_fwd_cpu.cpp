// CPU forward of the `blend` op (see blend.h and blend_tile_cpu.h).
//
// Tiles are shared out dynamically between OpenMP threads; each tile is processed by
// forward_tile, compiled for the baseline ISA and (x86-64) for AVX2, chosen at run time
// (csrc/common/cpu_isa.h).
#include <torch/library.h>

#include <memory>

#include "../common/cpu_isa.h"
#include "blend.h"
#include "blend_tile_cpu.h"

namespace cobgs {
namespace {

using namespace blend_detail;
using math::kTilePixels;

template <typename T>
struct FwdArgs {
  const GaussPrep<T>* prep;
  const int64_t* off;      // tile_offsets
  const int32_t* ids;      // flat_ids
  const T* feat;           // [N, C]
  const T* bg;             // [C]
  const int32_t* labels;   // [H, W] or null
  int C, K, width, height, tiles_x;
  T* img;                  // [H, W, C]
  T* trans;                // [H, W]
  int32_t* n_contrib;      // [H, W]
  int32_t* pair_counts;    // [M, K] label statistics per tile-list entry
  T* pair_weights;         // [M, K]
};

// Per-thread state of the tile being rendered: structure of arrays with 32-bit lanes
// throughout, so the row loops vectorise.
template <typename T>
struct FwdScratch {
  alignas(64) T Tp[kTilePixels];
  alignas(64) int32_t last[kTilePixels];
  alignas(64) int32_t done[kTilePixels];
  alignas(64) int32_t tile_labels[kTilePixels];  // -1 outside the image
  alignas(64) T wrow[kTileSize];                 // α·T on one row segment (0: not blended)
  alignas(64) int32_t brow[kTileSize];           // blended mask of the row segment
  // Label statistics of the current entry, per lane (vectorised; summed once per entry)
  // for up to kLaneLabels labels; more labels take a scalar path.
  alignas(64) int32_t lane_cnt[kLaneLabels][kTileSize];
  alignas(64) T lane_w[kLaneLabels][kTileSize];
  std::vector<T> colour;  // channel-major [C][256]

  explicit FwdScratch(int C) : colour(size_t(kTilePixels) * C) {
    std::fill(&lane_cnt[0][0], &lane_cnt[0][0] + kLaneLabels * kTileSize, 0);
    std::fill(&lane_w[0][0], &lane_w[0][0] + kLaneLabels * kTileSize, T(0));
  }
};

template <typename T>
COBGS_ALWAYS_INLINE void forward_tile(const FwdArgs<T>& a, int64_t tile, FwdScratch<T>& s) {
  const T alpha_min = T(math::kAlphaMin), alpha_max = T(math::kAlphaMax);
  const T t_min = T(math::kTransmittanceMin);
  const int C = a.C, K = a.K;
  const bool lane_labels = a.labels != nullptr && K <= kLaneLabels;
  const int x0 = int(tile % a.tiles_x) * kTileSize, y0 = int(tile / a.tiles_x) * kTileSize;
  const int x1 = std::min(x0 + kTileSize, a.width), y1 = std::min(y0 + kTileSize, a.height);
  std::fill(s.Tp, s.Tp + kTilePixels, T(1));
  std::fill(s.last, s.last + kTilePixels, 0);
  std::fill(s.colour.begin(), s.colour.end(), T(0));
  // Pixels outside the image (edge tiles) start "done" so they never count as active.
  int active = 0;
  uint32_t live[kTileSize] = {0};  // per tile row: bit c set while pixel c is not done
  for (int p = 0; p < kTilePixels; ++p) {
    const bool inside = x0 + p % kTileSize < x1 && y0 + p / kTileSize < y1;
    s.done[p] = !inside;
    active += inside;
    live[p / kTileSize] |= uint32_t(inside) << (p % kTileSize);
  }
  if (a.labels) {
    std::fill(s.tile_labels, s.tile_labels + kTilePixels, -1);
    for (int py = y0; py < y1; ++py)
      for (int px = x0; px < x1; ++px)
        s.tile_labels[(py - y0) * kTileSize + (px - x0)] = a.labels[int64_t(py) * a.width + px];
  }

  const int64_t lo = a.off[tile], hi = a.off[tile + 1];
  for (int64_t j = lo; j < hi && active > 0; ++j) {
    if (j + kPrefetchAhead < hi) {
      const int32_t ahead = a.ids[j + kPrefetchAhead];
      COBGS_PREFETCH(&a.prep[ahead]);
      COBGS_PREFETCH(a.feat + int64_t(ahead) * C);
    }
    const int32_t gi = a.ids[j];
    const GaussPrep<T> g = a.prep[gi];
    const int gx0 = std::max(x0, g.x0), gx1 = std::min(x1, g.x1);
    const int gy0 = std::max(y0, g.y0), gy1 = std::min(y1, g.y1);
    if (gx0 >= gx1 || gy0 >= gy1) continue;
    const T* f = a.feat + int64_t(gi) * C;
    const int32_t rank = static_cast<int32_t>(j - lo + 1);
    const uint32_t cols = ((uint32_t(1) << (gx1 - gx0)) - 1) << (gx0 - x0);
    // Row segments start and end on multiples of 4 columns of the tile, so the vectorised
    // loops run whole SIMD blocks. The extra pixels lie outside the conservative box (the
    // exact test rejects them) or outside the image (done).
    const int c0 = (gx0 - x0) & ~3;
    const int nx = std::min(kTileSize, ((gx1 - x0) + 3) & ~3) - c0;
    const int sx = x0 + c0;  // image column of the segment's first pixel
    bool entry_hit = false;  // the label lane sums hold something to flush
    for (int py = gy0; py < gy1; ++py) {
      // Rows whose pixels in the box have all stopped cost nothing (most rows once a tile
      // is mostly opaque: pixels stop after ~20 of their ~300 candidates).
      if (!(live[py - y0] & cols)) continue;
      const T dy = (T(py) + T(0.5)) - g.my;
      const int base = (py - y0) * kTileSize + c0;  // tile index of the segment start
      T* tp = s.Tp + base;
      int32_t* ls = s.last + base;
      int32_t* dn = s.done + base;
      int stops = 0;
      // The per-pixel rule of 3DGS (see reference.py), branch-free over the row.
      for (int k = 0; k < nx; ++k) {
        const T dx = (T(sx + k) + T(0.5)) - g.mx;
        const T power = math::pixel_power(g.ca, g.cb, g.cc, dx, dy);
        const T alpha = std::min(alpha_max, g.o * math::gauss_exp(power));
        const T t_old = tp[k];
        const T test_t = t_old * (T(1) - alpha);
        const int32_t cand = mask32(dn[k] == 0) & mask32(power <= T(0)) &
                             mask32(power >= g.power_reject) & mask32(alpha >= alpha_min);
        const int32_t low = mask32(test_t < t_min);  // not blended; the pixel stops
        const int32_t blend = cand & ~low;
        dn[k] |= cand & low & 1;
        stops += cand & low & 1;
        tp[k] = blend ? test_t : t_old;
        s.wrow[k] = blend ? alpha * t_old : T(0);
        s.brow[k] = blend;
      }
      int32_t any = 0;
      for (int k = 0; k < nx; ++k) {
        ls[k] = s.brow[k] ? rank : ls[k];
        any |= s.brow[k];
      }
      if (stops) {
        active -= stops;
        for (int k = 0; k < nx; ++k)
          if (dn[k]) live[py - y0] &= ~(uint32_t(1) << (c0 + k));
      }
      if (!any) continue;
      for (int c = 0; c < C; ++c) {
        const T fc = f[c];
        T* col = s.colour.data() + size_t(c) * kTilePixels + base;
        for (int k = 0; k < nx; ++k) col[k] = s.wrow[k] > T(0) ? col[k] + fc * s.wrow[k] : col[k];
      }
      if (lane_labels) {
        entry_hit = true;
        const int32_t* lab = s.tile_labels + base;
        for (int l = 0; l < K; ++l)
          for (int k = 0; k < nx; ++k) {
            const int32_t hit = s.brow[k] & mask32(lab[k] == l);
            const T w = s.wrow[k];  // loaded unconditionally so that the select vectorises
            s.lane_cnt[l][k] += hit & 1;
            s.lane_w[l][k] += hit ? w : T(0);
          }
      } else if (a.labels) {
        const int32_t* lab = s.tile_labels + base;
        for (int k = 0; k < nx; ++k) {
          if (!s.brow[k] || lab[k] < 0) continue;
          a.pair_counts[j * K + lab[k]] += 1;
          a.pair_weights[j * K + lab[k]] += s.wrow[k];
        }
      }
    }
    if (entry_hit) {
      for (int l = 0; l < K; ++l) {
        a.pair_counts[j * K + l] = lane_sum(s.lane_cnt[l], kTileSize);
        a.pair_weights[j * K + l] = lane_sum(s.lane_w[l], kTileSize);
        std::fill(s.lane_cnt[l], s.lane_cnt[l] + kTileSize, 0);
        std::fill(s.lane_w[l], s.lane_w[l] + kTileSize, T(0));
      }
    }
  }

  for (int py = y0; py < y1; ++py)
    for (int px = x0; px < x1; ++px) {
      const int p = (py - y0) * kTileSize + (px - x0);
      const int64_t pix = int64_t(py) * a.width + px;
      for (int c = 0; c < C; ++c)
        a.img[pix * C + c] = s.colour[size_t(c) * kTilePixels + p] + s.Tp[p] * a.bg[c];
      a.trans[pix] = s.Tp[p];
      a.n_contrib[pix] = s.last[p];
    }
}

// The instantiations the dispatcher picks from.
void forward_tile_base(const FwdArgs<float>& a, int64_t t, FwdScratch<float>& s) {
  forward_tile(a, t, s);
}
#if COBGS_AVX2_CLONES
COBGS_TARGET_AVX2 void forward_tile_avx2(const FwdArgs<float>& a, int64_t t,
                                         FwdScratch<float>& s) {
  forward_tile(a, t, s);
}
#endif
void forward_tile_base(const FwdArgs<double>& a, int64_t t, FwdScratch<double>& s) {
  forward_tile(a, t, s);
}

template <typename T>
using ForwardTileFn = void (*)(const FwdArgs<T>&, int64_t, FwdScratch<T>&);

inline ForwardTileFn<float> pick_forward_tile(float) {
#if COBGS_AVX2_CLONES
  if (cpu_use_avx2()) return &forward_tile_avx2;
#endif
  return static_cast<ForwardTileFn<float>>(&forward_tile_base);
}
inline ForwardTileFn<double> pick_forward_tile(double) {
  return static_cast<ForwardTileFn<double>>(&forward_tile_base);
}

template <typename T>
void blend_forward(const at::Tensor& means2d, const at::Tensor& conics,
                   const at::Tensor& opacities, const at::Tensor& features,
                   const at::Tensor& background, const at::Tensor& tile_offsets,
                   const at::Tensor& flat_ids, int width, int height, const int32_t* labels,
                   int num_labels, at::Tensor& image, at::Tensor& trans, at::Tensor& n_contrib,
                   at::Tensor& label_counts, at::Tensor& label_weights) {
  const int64_t n = means2d.size(0);
  const int64_t m = flat_ids.numel();
  const int C = static_cast<int>(features.size(1));
  const int K = num_labels;
  const int tiles_x = (width + kTileSize - 1) / kTileSize;
  const int64_t n_tiles = int64_t(tiles_x) * ((height + kTileSize - 1) / kTileSize);
  GaussPrep<T>* prep = reusable_buffer<GaussPrep<T>, 0>(n);  // filled in the region
  const T* m2_ptr = means2d.data_ptr<T>();
  const T* conic_ptr = conics.data_ptr<T>();
  const T* opacity_ptr = opacities.data_ptr<T>();
  // Label statistics per tile-list entry (each written only by the thread owning its
  // tile), summed per Gaussian afterwards in list order: no atomics, deterministic.
  const size_t pairs = labels ? size_t(m) * K : 0;
  int32_t* pair_counts = reusable_buffer<int32_t, 1>(pairs);
  T* pair_weights = reusable_buffer<T, 2>(pairs);
  std::fill(pair_counts, pair_counts + pairs, 0);
  std::fill(pair_weights, pair_weights + pairs, T(0));

  FwdArgs<T> a;
  a.prep = prep;
  a.off = tile_offsets.data_ptr<int64_t>();
  a.ids = flat_ids.data_ptr<int32_t>();
  a.feat = features.data_ptr<T>();
  a.bg = background.data_ptr<T>();
  a.labels = labels;
  a.C = C;
  a.K = K;
  a.width = width;
  a.height = height;
  a.tiles_x = tiles_x;
  a.img = image.data_ptr<T>();
  a.trans = trans.data_ptr<T>();
  a.n_contrib = n_contrib.data_ptr<int32_t>();
  a.pair_counts = pair_counts;
  a.pair_weights = pair_weights;
  const ForwardTileFn<T> tile_fn = pick_forward_tile(T(0));

#pragma omp parallel num_threads(cpu_threads())
  {
    prepare<T>(m2_ptr, conic_ptr, opacity_ptr, n, prep);  // ends with a barrier
    std::unique_ptr<FwdScratch<T>> scratch(new FwdScratch<T>(C));
#pragma omp for schedule(dynamic, 1)
    for (int64_t tile = 0; tile < n_tiles; ++tile) tile_fn(a, tile, *scratch);
  }

  if (labels) {
    int32_t* cnt = label_counts.data_ptr<int32_t>();
    float* wts = label_weights.data_ptr<float>();
    T* wsum = reusable_buffer<T, 3>(size_t(n) * K);
    std::fill(wsum, wsum + size_t(n) * K, T(0));
    std::fill(cnt, cnt + size_t(n) * K, 0);
    for (int64_t j = 0; j < m; ++j) {
      const int32_t* pc = pair_counts + j * K;
      int32_t total = 0;
      for (int k = 0; k < K; ++k) total |= pc[k];
      if (total == 0) continue;  // the entry contributed to no labelled pixel
      const int64_t g = a.ids[j];
      for (int k = 0; k < K; ++k) {
        cnt[g * K + k] += pc[k];
        wsum[g * K + k] += pair_weights[j * K + k];
      }
    }
    for (size_t i = 0; i < size_t(n) * K; ++i) wts[i] = static_cast<float>(wsum[i]);
  }
}

}  // namespace

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> blend_cpu(
    const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
    const at::Tensor& features, const at::Tensor& background, const at::Tensor& tile_offsets,
    const at::Tensor& flat_ids, int64_t width, int64_t height,
    const std::optional<at::Tensor>& pixel_labels, int64_t num_labels) {
  check_blend_inputs(means2d, conics, opacities, features, background, tile_offsets,
                     flat_ids, width, height);
  TORCH_CHECK(num_labels >= 1, "num_labels must be >= 1, got ", num_labels);
  const int64_t n = means2d.size(0), c = features.size(1);
  const int32_t* labels = nullptr;
  if (pixel_labels.has_value()) {
    const at::Tensor& pl = *pixel_labels;
    COBGS_CHECK_INPUT(pl);
    COBGS_CHECK_DTYPE(pl, at::kInt);
    COBGS_CHECK_SHAPE(pl, height, width);
    labels = pl.data_ptr<int32_t>();
    bool ok = true;
    for (int64_t i = 0; i < pl.numel(); ++i) ok &= (labels[i] >= -1) & (labels[i] < num_labels);
    TORCH_CHECK(ok, "pixel_labels must lie in -1..", num_labels - 1);
  }
  const auto opts = means2d.options();
  at::Tensor image = at::empty({height, width, c}, opts);
  at::Tensor trans = at::empty({height, width}, opts);
  at::Tensor n_contrib = at::empty({height, width}, opts.dtype(at::kInt));
  const int64_t rows = labels ? n : 0;
  // Filled completely by blend_forward (empty + a plain loop: no extra ATen kernel).
  at::Tensor label_counts = at::empty({rows, num_labels}, opts.dtype(at::kInt));
  at::Tensor label_weights = at::empty({rows, num_labels}, opts.dtype(at::kFloat));
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "cobgs::blend", [&] {
    blend_forward<scalar_t>(means2d, conics, opacities, features, background, tile_offsets,
                            flat_ids, static_cast<int>(width), static_cast<int>(height),
                            labels, static_cast<int>(num_labels), image, trans, n_contrib,
                            label_counts, label_weights);
  });
  return {image, trans, n_contrib, label_counts, label_weights};
}

TORCH_LIBRARY_IMPL(cobgs, CPU, m) { m.impl("blend", &blend_cpu); }

}  // namespace cobgs
