// CPU backward of the `blend` op (see blend.h and blend_tile_cpu.h).
//
// Per pixel, walking its contributors back to front from T_final (3DGS): the
// transmittance in front of Gaussian g is recovered as T_g = T_after / (1 - α_g), and
//   dC/dα_g = T_g (f_g - R_g),   R_g = colour behind g per unit transmittance, updated
//   R ← α_g f_g + (1 - α_g) R (starting from the background);
//   dT_final/dα_g = -T_final / (1 - α_g);
//   α = min(0.99, o G), G = exp(power): no gradient where the clamp is active.
#include <torch/library.h>

#include <memory>

#include "blend.h"
#include "blend_tile_cpu.h"

namespace cobgs {
namespace {

using namespace blend_detail;

// Gradient slot layout of one tile-list entry.
constexpr int kMx = 0, kMy = 1, kCa = 2, kCb = 3, kCc = 4, kOp = 5, kFeat = 6;

template <typename T>
void blend_backward(const at::Tensor& means2d, const at::Tensor& conics,
                    const at::Tensor& opacities, const at::Tensor& features,
                    const at::Tensor& background, const at::Tensor& tile_offsets,
                    const at::Tensor& flat_ids, const at::Tensor& transmittance,
                    const at::Tensor& n_contrib, const at::Tensor& v_image,
                    const at::Tensor& v_trans, at::Tensor& v_means2d, at::Tensor& v_conics,
                    at::Tensor& v_opacities, at::Tensor& v_features, at::Tensor& v_background) {
  const int64_t n = means2d.size(0);
  const int C = static_cast<int>(features.size(1));
  const int S = kFeat + C;  // gradient slots per tile-list entry
  const int width = static_cast<int>(transmittance.size(1));
  const int height = static_cast<int>(transmittance.size(0));
  const int tiles_x = (width + kTileSize - 1) / kTileSize;
  const int tiles_y = (height + kTileSize - 1) / kTileSize;
  const int64_t n_tiles = int64_t(tiles_x) * tiles_y;
  const int64_t* off = tile_offsets.data_ptr<int64_t>();
  const int32_t* ids = flat_ids.data_ptr<int32_t>();
  const int64_t m = flat_ids.numel();
  const T* feat = features.data_ptr<T>();
  const T* bg = background.data_ptr<T>();
  const T* tr = transmittance.data_ptr<T>();
  const int32_t* nc = n_contrib.data_ptr<int32_t>();
  const T* vimg = v_image.data_ptr<T>();
  const T* vtr = v_trans.data_ptr<T>();
  const auto prep = prepare<T>(means2d.data_ptr<T>(), conics.data_ptr<T>(),
                               opacities.data_ptr<T>(), n);
  // Every entry of a non-empty tile is written by the thread owning the tile.
  std::unique_ptr<T[]> pair_grad(new T[size_t(m) * S]);

  const T alpha_min = T(math::kAlphaMin), alpha_max = T(math::kAlphaMax);

#pragma omp parallel num_threads(cpu_threads())
  {
    // Per-pixel state of the tile (structure of arrays, channel-major where per channel).
    alignas(64) T Tp[math::kTilePixels];   // transmittance behind the current Gaussian
    alignas(64) T vtt[math::kTilePixels];  // dL/dT_final · T_final
    alignas(64) int32_t last[math::kTilePixels];
    std::vector<T> rest(size_t(math::kTilePixels) * C);  // R per channel and pixel
    std::vector<T> vcol(size_t(math::kTilePixels) * C);  // dL/dimage per channel and pixel
    // Quantities of one row segment, and per-lane gradient sums of the current entry
    // (lane = column offset in the Gaussian's box; summed over lanes at the end of the
    // entry, a fixed order, so results do not depend on vectorisation or threads).
    alignas(64) T r_alpha[kTileSize], r_om[kTileSize], r_tf[kTileSize], r_dot[kTileSize];
    alignas(64) T r_gauss[kTileSize];
    alignas(64) int32_t r_ok[kTileSize];
    std::vector<T> lanes(size_t(S) * kTileSize, T(0));  // zero between entries

#pragma omp for schedule(dynamic, 1)
    for (int64_t tile = 0; tile < n_tiles; ++tile) {
      const int64_t lo = off[tile], hi = off[tile + 1];
      if (lo == hi) continue;
      std::fill(pair_grad.get() + lo * S, pair_grad.get() + hi * S, T(0));
      const int x0 = int(tile % tiles_x) * kTileSize, y0 = int(tile / tiles_x) * kTileSize;
      const int x1 = std::min(x0 + kTileSize, width), y1 = std::min(y0 + kTileSize, height);
      int max_last = 0;
      int32_t row_last[kTileSize] = {0};  // per tile row: the largest n_contrib
      // Pixels outside the image (edge tiles) are never blended (n_contrib 0) but do sit
      // in the SIMD blocks: give them finite state so masked lanes stay exactly zero.
      std::fill(last, last + math::kTilePixels, 0);
      std::fill(Tp, Tp + math::kTilePixels, T(1));
      std::fill(vtt, vtt + math::kTilePixels, T(0));
      std::fill(rest.begin(), rest.end(), T(0));
      std::fill(vcol.begin(), vcol.end(), T(0));
      for (int py = y0; py < y1; ++py)
        for (int px = x0; px < x1; ++px) {
          const int p = (py - y0) * kTileSize + (px - x0);
          const int64_t pix = int64_t(py) * width + px;
          Tp[p] = tr[pix];
          vtt[p] = vtr[pix] * tr[pix];
          last[p] = nc[pix];
          max_last = std::max(max_last, last[p]);
          row_last[py - y0] = std::max(row_last[py - y0], last[p]);
          for (int c = 0; c < C; ++c) {
            rest[size_t(c) * math::kTilePixels + p] = bg[c];
            vcol[size_t(c) * math::kTilePixels + p] = vimg[pix * C + c];
          }
        }
      for (int64_t rank = max_last - 1; rank >= 0; --rank) {
        const int64_t j = lo + rank;
        if (rank >= kPrefetchAhead) {
          const int32_t ahead = ids[j - kPrefetchAhead];
          COBGS_PREFETCH(&prep[ahead]);
          COBGS_PREFETCH(feat + int64_t(ahead) * C);
        }
        const int32_t gi = ids[j];
        const GaussPrep<T> g = prep[gi];
        const int gx0 = std::max(x0, g.x0), gx1 = std::min(x1, g.x1);
        const int gy0 = std::max(y0, g.y0), gy1 = std::min(y1, g.y1);
        if (gx0 >= gx1 || gy0 >= gy1) continue;
        const T* f = feat + int64_t(gi) * C;
        // Whole 4-column blocks, as in the forward pass.
        const int c0 = (gx0 - x0) & ~3;
        const int nx = std::min(kTileSize, ((gx1 - x0) + 3) & ~3) - c0;
        const int sx = x0 + c0;
        const int32_t rank32 = static_cast<int32_t>(rank);
        bool entry_hit = false;  // lanes hold something (they are all zero otherwise)
        T* l_mx = lanes.data() + kMx * kTileSize;
        T* l_my = lanes.data() + kMy * kTileSize;
        T* l_ca = lanes.data() + kCa * kTileSize;
        T* l_cb = lanes.data() + kCb * kTileSize;
        T* l_cc = lanes.data() + kCc * kTileSize;
        T* l_op = lanes.data() + kOp * kTileSize;
        for (int py = gy0; py < gy1; ++py) {
          // A row where this entry lies behind every pixel's last contributor: nothing to do.
          if (rank32 >= row_last[py - y0]) continue;
          const T dy = (T(py) + T(0.5)) - g.my;
          const int base = (py - y0) * kTileSize + c0;
          T* tp = Tp + base;
          const int32_t* ls = last + base;
          // 1. Which pixels of the row this Gaussian was blended into, and its α there
          //    (the forward's decision, recomputed bit for bit). Loops are written with
          //    int32 masks, unconditional loads and at most two selects each, the shape
          //    GCC 12 if-converts and vectorises.
          for (int k = 0; k < nx; ++k) {
            const T dx = (T(sx + k) + T(0.5)) - g.mx;
            const T power = math::pixel_power(g.ca, g.cb, g.cc, dx, dy);
            const T gauss = math::gauss_exp(power);
            const T alpha = std::min(alpha_max, g.o * gauss);
            const int32_t ok = mask32(rank32 < ls[k]) & mask32(power <= T(0)) &
                               mask32(power >= g.power_reject) & mask32(alpha >= alpha_min);
            const T one_minus = T(1) - alpha;
            const T t_after = tp[k];
            const T t_front = t_after / one_minus;  // T in front of this Gaussian
            tp[k] = ok ? t_front : t_after;
            r_ok[k] = ok;
            r_alpha[k] = alpha;
            r_om[k] = one_minus;
            r_tf[k] = t_front;
            r_gauss[k] = gauss;
            r_dot[k] = T(0);
          }
          int32_t any = 0;
          for (int k = 0; k < nx; ++k) any |= r_ok[k];
          if (!any) continue;  // nothing of this Gaussian was blended on this row
          entry_hit = true;
          // 2. Per channel: dL/df = α T dL/dC, Σ_c (f_c - R_c) dL/dC_c, then
          //    R ← α f + (1 - α) R.
          for (int c = 0; c < C; ++c) {
            const T fc = f[c];
            T* r = rest.data() + size_t(c) * math::kTilePixels + base;
            const T* vc = vcol.data() + size_t(c) * math::kTilePixels + base;
            T* l_f = lanes.data() + (kFeat + c) * kTileSize;
            for (int k = 0; k < nx; ++k) {
              const T v = vc[k];                 // loaded unconditionally: a select
              const T v_ok = r_ok[k] ? v : T(0);  // of two values vectorises
              l_f[k] += r_alpha[k] * r_tf[k] * v_ok;
              r_dot[k] += (fc - r[k]) * v_ok;
            }
            for (int k = 0; k < nx; ++k) {
              const T rk = r[k];
              const T updated = r_alpha[k] * fc + r_om[k] * rk;
              r[k] = r_ok[k] ? updated : rk;
            }
          }
          // 3. dL/dα → opacity, conic and mean (no gradient where the 0.99 clamp is active).
          const T* vt = vtt + base;
          for (int k = 0; k < nx; ++k) {
            const T dx = (T(sx + k) + T(0.5)) - g.mx;
            const T gauss = r_gauss[k];
            const T o_g = g.o * gauss;
            const int32_t ok = r_ok[k] & mask32(o_g <= alpha_max);
            const T v_alpha_all = r_tf[k] * r_dot[k] - vt[k] / r_om[k];
            const T v_alpha = ok ? v_alpha_all : T(0);  // zero makes every term below zero
            const T v_power = o_g * v_alpha;
            l_op[k] += gauss * v_alpha;
            l_ca[k] += T(-0.5) * dx * dx * v_power;
            l_cb[k] += -dx * dy * v_power;
            l_cc[k] += T(-0.5) * dy * dy * v_power;
            // d = pixel - mean, so d(power)/d(mean) = -d(power)/d(d).
            l_mx[k] += (g.ca * dx + g.cb * dy) * v_power;
            l_my[k] += (g.cb * dx + g.cc * dy) * v_power;
          }
        }
        if (!entry_hit) continue;  // its slot stays zero
        T* dst = pair_grad.get() + j * S;
        for (int q = 0; q < S; ++q) {
          T* l = lanes.data() + size_t(q) * kTileSize;
          dst[q] = lane_sum(l, nx);
          std::fill(l, l + nx, T(0));
        }
      }
    }
  }

  // Fixed-order reduction of the per-entry gradients into per-Gaussian gradients.
  T* vm = v_means2d.data_ptr<T>();
  T* vco = v_conics.data_ptr<T>();
  T* vo = v_opacities.data_ptr<T>();
  T* vf = v_features.data_ptr<T>();
  for (int64_t j = 0; j < m; ++j) {
    const int64_t g = ids[j];
    const T* src = pair_grad.get() + j * S;
    vm[2 * g] += src[kMx];
    vm[2 * g + 1] += src[kMy];
    vco[3 * g] += src[kCa];
    vco[3 * g + 1] += src[kCb];
    vco[3 * g + 2] += src[kCc];
    vo[g] += src[kOp];
    for (int c = 0; c < C; ++c) vf[g * C + c] += src[kFeat + c];
  }
  // image = ... + T_final · background.
  T* vb = v_background.data_ptr<T>();
  const int64_t pixels = int64_t(width) * height;
  for (int c = 0; c < C; ++c) {
    double s = 0.0;
    for (int64_t pix = 0; pix < pixels; ++pix) s += double(tr[pix]) * double(vimg[pix * C + c]);
    vb[c] = static_cast<T>(s);
  }
}

}  // namespace

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> blend_bwd_cpu(
    const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
    const at::Tensor& features, const at::Tensor& background, const at::Tensor& tile_offsets,
    const at::Tensor& flat_ids, const at::Tensor& transmittance, const at::Tensor& n_contrib,
    const at::Tensor& v_image, const at::Tensor& v_transmittance) {
  TORCH_CHECK(transmittance.dim() == 2, "transmittance must have shape [H, W], got ",
              transmittance.sizes());
  const int64_t height = transmittance.size(0), width = transmittance.size(1);
  check_blend_inputs(means2d, conics, opacities, features, background, tile_offsets,
                     flat_ids, width, height);
  const int64_t c = features.size(1);
  COBGS_CHECK_INPUT(transmittance);
  COBGS_CHECK_INPUT(n_contrib);
  COBGS_CHECK_INPUT(v_image);
  COBGS_CHECK_INPUT(v_transmittance);
  COBGS_CHECK_DTYPE(transmittance, means2d.scalar_type());
  COBGS_CHECK_DTYPE(v_image, means2d.scalar_type());
  COBGS_CHECK_DTYPE(v_transmittance, means2d.scalar_type());
  COBGS_CHECK_DTYPE(n_contrib, at::kInt);
  COBGS_CHECK_SHAPE(n_contrib, height, width);
  COBGS_CHECK_SHAPE(v_image, height, width, c);
  COBGS_CHECK_SHAPE(v_transmittance, height, width);
  at::Tensor v_means2d = at::zeros_like(means2d);
  at::Tensor v_conics = at::zeros_like(conics);
  at::Tensor v_opacities = at::zeros_like(opacities);
  at::Tensor v_features = at::zeros_like(features);
  at::Tensor v_background = at::zeros_like(background);
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "cobgs::blend_bwd", [&] {
    blend_backward<scalar_t>(means2d, conics, opacities, features, background, tile_offsets,
                             flat_ids, transmittance, n_contrib, v_image, v_transmittance,
                             v_means2d, v_conics, v_opacities, v_features, v_background);
  });
  return {v_means2d, v_conics, v_opacities, v_features, v_background};
}

TORCH_LIBRARY_IMPL(cobgs, CPU, m) { m.impl("blend_bwd", &blend_bwd_cpu); }

}  // namespace cobgs
