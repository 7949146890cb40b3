// CPU forward of the `blend` op (see blend.h and blend_tile_cpu.h).
#include <torch/library.h>

#include <cstring>

#include "blend.h"
#include "blend_tile_cpu.h"

namespace cobgs {
namespace {

using namespace blend_detail;

template <typename T>
void blend_forward(const at::Tensor& means2d, const at::Tensor& conics,
                   const at::Tensor& opacities, const at::Tensor& features,
                   const at::Tensor& background, const at::Tensor& tile_offsets,
                   const at::Tensor& flat_ids, int width, int height, const int32_t* labels,
                   int num_labels, at::Tensor& image, at::Tensor& trans, at::Tensor& n_contrib,
                   at::Tensor& label_counts, at::Tensor& label_weights) {
  const int64_t n = means2d.size(0);
  const int C = static_cast<int>(features.size(1));
  const int K = num_labels;
  const int tiles_x = (width + kTileSize - 1) / kTileSize;
  const int tiles_y = (height + kTileSize - 1) / kTileSize;
  const int64_t n_tiles = int64_t(tiles_x) * tiles_y;
  const int64_t* off = tile_offsets.data_ptr<int64_t>();
  const int32_t* ids = flat_ids.data_ptr<int32_t>();
  const int64_t m = flat_ids.numel();
  const T* feat = features.data_ptr<T>();
  const T* bg = background.data_ptr<T>();
  T* img = image.data_ptr<T>();
  T* tr = trans.data_ptr<T>();
  int32_t* nc = n_contrib.data_ptr<int32_t>();
  const auto prep = prepare<T>(means2d.data_ptr<T>(), conics.data_ptr<T>(),
                               opacities.data_ptr<T>(), n);

  // Label statistics per tile-list entry (each written by the one thread owning the
  // tile), summed per Gaussian afterwards in list order.
  std::vector<int32_t> pair_counts(labels ? m * K : 0);
  std::vector<T> pair_weights(labels ? m * K : 0);

  const T alpha_min = T(math::kAlphaMin), alpha_max = T(math::kAlphaMax);
  const T t_min = T(math::kTransmittanceMin);

#pragma omp parallel num_threads(cpu_threads())
  {
    // Per-pixel state of the tile, structure of arrays; 32-bit lanes throughout so the
    // row loops below vectorise.
    alignas(64) T Tp[math::kTilePixels];
    alignas(64) int32_t last[math::kTilePixels];
    alignas(64) int32_t done[math::kTilePixels];
    alignas(64) T wrow[kTileSize];        // α·T of one row segment (0: not blended)
    alignas(64) int32_t brow[kTileSize];  // blended mask of the row segment
    std::vector<T> colour(size_t(math::kTilePixels) * C);  // channel-major [C][256]
    // Label statistics: the tile's labels (-1 outside the image) and, for up to
    // kLaneLabels labels, per-lane sums of the current entry (vectorised; reduced once
    // per entry). More labels take a scalar path.
    alignas(64) int32_t tile_labels[math::kTilePixels];
    const bool lane_labels = labels && K <= kLaneLabels;
    alignas(64) int32_t lane_cnt[kLaneLabels][kTileSize] = {};
    alignas(64) T lane_w[kLaneLabels][kTileSize] = {};

#pragma omp for schedule(dynamic, 1)
    for (int64_t tile = 0; tile < n_tiles; ++tile) {
      const int x0 = int(tile % tiles_x) * kTileSize, y0 = int(tile / tiles_x) * kTileSize;
      const int x1 = std::min(x0 + kTileSize, width), y1 = std::min(y0 + kTileSize, height);
      std::fill(Tp, Tp + math::kTilePixels, T(1));
      std::fill(last, last + math::kTilePixels, 0);
      std::fill(colour.begin(), colour.end(), T(0));
      // Pixels outside the image (edge tiles) start "done" so they never count as active.
      int active = 0;
      uint32_t live[kTileSize] = {0};  // per tile row: bit c set while pixel c is not done
      for (int p = 0; p < math::kTilePixels; ++p) {
        const bool inside = x0 + p % kTileSize < x1 && y0 + p / kTileSize < y1;
        done[p] = !inside;
        active += inside;
        live[p / kTileSize] |= uint32_t(inside) << (p % kTileSize);
      }
      if (labels) {
        std::fill(tile_labels, tile_labels + math::kTilePixels, -1);
        for (int py = y0; py < y1; ++py)
          for (int px = x0; px < x1; ++px)
            tile_labels[(py - y0) * kTileSize + (px - x0)] = labels[int64_t(py) * width + px];
      }
      const int64_t lo = off[tile], hi = off[tile + 1];
      for (int64_t j = lo; j < hi && active > 0; ++j) {
        if (j + kPrefetchAhead < hi) {
          const int32_t ahead = ids[j + kPrefetchAhead];
          COBGS_PREFETCH(&prep[ahead]);
          COBGS_PREFETCH(feat + int64_t(ahead) * C);
        }
        const int32_t gi = ids[j];
        const GaussPrep<T> g = prep[gi];
        const int gx0 = std::max(x0, g.x0), gx1 = std::min(x1, g.x1);
        const int gy0 = std::max(y0, g.y0), gy1 = std::min(y1, g.y1);
        if (gx0 >= gx1 || gy0 >= gy1) continue;
        const T* f = feat + int64_t(gi) * C;
        const int32_t rank = static_cast<int32_t>(j - lo + 1);
        const uint32_t cols = ((uint32_t(1) << (gx1 - gx0)) - 1) << (gx0 - x0);
        // Row segments start and end on multiples of 4 columns of the tile, so the
        // vectorised loops run whole SIMD blocks. The extra pixels lie outside the
        // conservative box (the exact test rejects them) or outside the image (done).
        const int c0 = (gx0 - x0) & ~3;
        const int nx = std::min(kTileSize, ((gx1 - x0) + 3) & ~3) - c0;
        const int sx = x0 + c0;  // image column of the segment's first pixel
        bool entry_hit = false;  // lane sums hold something to flush
        for (int py = gy0; py < gy1; ++py) {
          // Rows whose pixels in the box have all stopped cost nothing (most rows, once a
          // tile is mostly opaque: pixels stop after ~20 of their ~300 candidates).
          if (!(live[py - y0] & cols)) continue;
          const T dy = (T(py) + T(0.5)) - g.my;
          const int base = (py - y0) * kTileSize + c0;  // tile index of the segment start
          T* tp = Tp + base;
          int32_t* ls = last + base;
          int32_t* dn = done + base;
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
            wrow[k] = blend ? alpha * t_old : T(0);
            brow[k] = blend;
          }
          for (int k = 0; k < nx; ++k) ls[k] = brow[k] ? rank : ls[k];
          active -= stops;
          if (stops)
            for (int k = 0; k < nx; ++k)
              if (dn[k]) live[py - y0] &= ~(uint32_t(1) << (c0 + k));
          for (int c = 0; c < C; ++c) {
            const T fc = f[c];
            T* col = colour.data() + size_t(c) * math::kTilePixels + base;
            for (int k = 0; k < nx; ++k) col[k] = wrow[k] > T(0) ? col[k] + fc * wrow[k] : col[k];
          }
          int32_t any = 0;
          for (int k = 0; k < nx; ++k) any |= brow[k];
          if (lane_labels && any) {
            entry_hit = true;
            const int32_t* lab = tile_labels + base;
            for (int l = 0; l < K; ++l)
              for (int k = 0; k < nx; ++k) {
                const int32_t hit = brow[k] & mask32(lab[k] == l);
                const T w = wrow[k];  // loaded unconditionally so the select vectorises
                lane_cnt[l][k] += hit & 1;
                lane_w[l][k] += hit ? w : T(0);
              }
          } else if (labels && any) {
            const int32_t* lab = tile_labels + base;
            for (int k = 0; k < nx; ++k) {
              if (!brow[k] || lab[k] < 0) continue;
              pair_counts[j * K + lab[k]] += 1;
              pair_weights[j * K + lab[k]] += wrow[k];
            }
          }
        }
        if (entry_hit) {
          for (int l = 0; l < K; ++l) {
            pair_counts[j * K + l] = lane_sum(lane_cnt[l], kTileSize);
            pair_weights[j * K + l] = lane_sum(lane_w[l], kTileSize);
            std::fill(lane_cnt[l], lane_cnt[l] + kTileSize, 0);
            std::fill(lane_w[l], lane_w[l] + kTileSize, T(0));
          }
        }
      }
      for (int py = y0; py < y1; ++py)
        for (int px = x0; px < x1; ++px) {
          const int p = (py - y0) * kTileSize + (px - x0);
          const int64_t pix = int64_t(py) * width + px;
          for (int c = 0; c < C; ++c)
            img[pix * C + c] = colour[size_t(c) * math::kTilePixels + p] + Tp[p] * bg[c];
          tr[pix] = Tp[p];
          nc[pix] = last[p];
        }
    }
  }

  if (labels) {
    int32_t* cnt = label_counts.data_ptr<int32_t>();
    float* wts = label_weights.data_ptr<float>();
    std::vector<T> wsum(size_t(n) * K, T(0));
    for (int64_t j = 0; j < m; ++j) {
      const int64_t g = ids[j];
      for (int k = 0; k < K; ++k) {
        cnt[g * K + k] += pair_counts[j * K + k];
        wsum[g * K + k] += pair_weights[j * K + k];
      }
    }
    for (size_t i = 0; i < wsum.size(); ++i) wts[i] = static_cast<float>(wsum[i]);
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
  at::Tensor label_counts = at::zeros({rows, num_labels}, opts.dtype(at::kInt));
  at::Tensor label_weights = at::zeros({rows, num_labels}, opts.dtype(at::kFloat));
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
