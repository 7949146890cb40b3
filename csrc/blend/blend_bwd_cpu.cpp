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

#include "../common/cpu_isa.h"
#include "blend.h"
#include "blend_tile_cpu.h"

namespace cobgs {
namespace {

using namespace blend_detail;
using math::kTilePixels;

// Gradient slot layout of one tile-list entry.
constexpr int kMx = 0, kMy = 1, kCa = 2, kCb = 3, kCc = 4, kOp = 5, kFeat = 6;

template <typename T>
struct BwdArgs {
  const GaussPrep<T>* prep;
  const int64_t* off;       // tile_offsets
  const int32_t* ids;       // flat_ids
  const T* feat;            // [N, C]
  const T* bg;              // [C]
  const T* trans;           // [H, W] T_final
  const int32_t* n_contrib; // [H, W]
  const T* v_image;         // [H, W, C]
  const T* v_trans;         // [H, W]
  int C, S, width, height, tiles_x;
  T* pair_grad;             // [M, S] gradient slots per tile-list entry
};

// Per-thread state of the tile (structure of arrays, channel-major where per channel).
template <typename T>
struct BwdScratch {
  alignas(64) T Tp[kTilePixels];   // transmittance behind the current Gaussian
  alignas(64) T vtt[kTilePixels];  // dL/dT_final · T_final
  alignas(64) int32_t last[kTilePixels];
  // Quantities of one row segment.
  alignas(64) T r_alpha[kTileSize], r_om[kTileSize], r_tf[kTileSize], r_dot[kTileSize];
  alignas(64) T r_gauss[kTileSize];
  alignas(64) int32_t r_ok[kTileSize];
  std::vector<T> rest;   // R per channel and pixel
  std::vector<T> vcol;   // dL/dimage per channel and pixel
  // Per-lane gradient sums of the current entry (lane = column in the row segment),
  // summed over lanes at the end of the entry in a fixed order (lane_sum), so results do
  // not depend on the SIMD width or the threads. All zero between entries.
  std::vector<T> lanes;

  BwdScratch(int C, int S)
      : rest(size_t(kTilePixels) * C), vcol(size_t(kTilePixels) * C),
        lanes(size_t(S) * kTileSize, T(0)) {}
};

template <typename T>
COBGS_ALWAYS_INLINE void backward_tile(const BwdArgs<T>& a, int64_t tile, BwdScratch<T>& s) {
  const T alpha_min = T(math::kAlphaMin), alpha_max = T(math::kAlphaMax);
  const int C = a.C, S = a.S;
  const int64_t lo = a.off[tile], hi = a.off[tile + 1];
  if (lo == hi) return;
  std::fill(a.pair_grad + lo * S, a.pair_grad + hi * S, T(0));
  const int x0 = int(tile % a.tiles_x) * kTileSize, y0 = int(tile / a.tiles_x) * kTileSize;
  const int x1 = std::min(x0 + kTileSize, a.width), y1 = std::min(y0 + kTileSize, a.height);
  int max_last = 0;
  int32_t row_last[kTileSize] = {0};  // per tile row: the largest n_contrib
  // Pixels outside the image (edge tiles) are never blended (n_contrib 0) but do sit
  // in the SIMD blocks: give them finite state so masked lanes stay exactly zero.
  std::fill(s.last, s.last + kTilePixels, 0);
  std::fill(s.Tp, s.Tp + kTilePixels, T(1));
  std::fill(s.vtt, s.vtt + kTilePixels, T(0));
  std::fill(s.rest.begin(), s.rest.end(), T(0));
  std::fill(s.vcol.begin(), s.vcol.end(), T(0));
  for (int py = y0; py < y1; ++py)
    for (int px = x0; px < x1; ++px) {
      const int p = (py - y0) * kTileSize + (px - x0);
      const int64_t pix = int64_t(py) * a.width + px;
      s.Tp[p] = a.trans[pix];
      s.vtt[p] = a.v_trans[pix] * a.trans[pix];
      s.last[p] = a.n_contrib[pix];
      max_last = std::max(max_last, s.last[p]);
      row_last[py - y0] = std::max(row_last[py - y0], s.last[p]);
      for (int c = 0; c < C; ++c) {
        s.rest[size_t(c) * kTilePixels + p] = a.bg[c];
        s.vcol[size_t(c) * kTilePixels + p] = a.v_image[pix * C + c];
      }
    }
  for (int64_t rank = max_last - 1; rank >= 0; --rank) {
    const int64_t j = lo + rank;
    if (rank >= kPrefetchAhead) {
      const int32_t ahead = a.ids[j - kPrefetchAhead];
      COBGS_PREFETCH(&a.prep[ahead]);
      COBGS_PREFETCH(a.feat + int64_t(ahead) * C);
    }
    const int32_t gi = a.ids[j];
    const GaussPrep<T> g = a.prep[gi];
    const int gx0 = std::max(x0, g.x0), gx1 = std::min(x1, g.x1);
    const int gy0 = std::max(y0, g.y0), gy1 = std::min(y1, g.y1);
    if (gx0 >= gx1 || gy0 >= gy1) continue;
    const T* f = a.feat + int64_t(gi) * C;
    // Whole 4-column blocks, as in the forward pass.
    const int c0 = (gx0 - x0) & ~3;
    const int nx = std::min(kTileSize, ((gx1 - x0) + 3) & ~3) - c0;
    const int sx = x0 + c0;
    const int32_t rank32 = static_cast<int32_t>(rank);
    bool entry_hit = false;  // lanes hold something (they are all zero otherwise)
    T* l_mx = s.lanes.data() + kMx * kTileSize;
    T* l_my = s.lanes.data() + kMy * kTileSize;
    T* l_ca = s.lanes.data() + kCa * kTileSize;
    T* l_cb = s.lanes.data() + kCb * kTileSize;
    T* l_cc = s.lanes.data() + kCc * kTileSize;
    T* l_op = s.lanes.data() + kOp * kTileSize;
    for (int py = gy0; py < gy1; ++py) {
      // A row where this entry lies behind every pixel's last contributor: nothing to do.
      if (rank32 >= row_last[py - y0]) continue;
      const T dy = (T(py) + T(0.5)) - g.my;
      const int base = (py - y0) * kTileSize + c0;
      T* tp = s.Tp + base;
      const int32_t* ls = s.last + base;
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
        s.r_ok[k] = ok;
        s.r_alpha[k] = alpha;
        s.r_om[k] = one_minus;
        s.r_tf[k] = t_front;
        s.r_gauss[k] = gauss;
        s.r_dot[k] = T(0);
      }
      int32_t any = 0;
      for (int k = 0; k < nx; ++k) any |= s.r_ok[k];
      if (!any) continue;  // nothing of this Gaussian was blended on this row
      entry_hit = true;
      // 2. Per channel: dL/df = α T dL/dC, Σ_c (f_c - R_c) dL/dC_c, then
      //    R ← α f + (1 - α) R.
      for (int c = 0; c < C; ++c) {
        const T fc = f[c];
        T* r = s.rest.data() + size_t(c) * kTilePixels + base;
        const T* vc = s.vcol.data() + size_t(c) * kTilePixels + base;
        T* l_f = s.lanes.data() + (kFeat + c) * kTileSize;
        for (int k = 0; k < nx; ++k) {
          const T v = vc[k];                 // loaded unconditionally: a select
          const T v_ok = s.r_ok[k] ? v : T(0);  // of two values vectorises
          l_f[k] += s.r_alpha[k] * s.r_tf[k] * v_ok;
          s.r_dot[k] += (fc - r[k]) * v_ok;
        }
        for (int k = 0; k < nx; ++k) {
          const T rk = r[k];
          const T updated = s.r_alpha[k] * fc + s.r_om[k] * rk;
          r[k] = s.r_ok[k] ? updated : rk;
        }
      }
      // 3. dL/dα → opacity, conic and mean (no gradient where the 0.99 clamp is active).
      const T* vt = s.vtt + base;
      for (int k = 0; k < nx; ++k) {
        const T dx = (T(sx + k) + T(0.5)) - g.mx;
        const T gauss = s.r_gauss[k];
        const T o_g = g.o * gauss;
        const int32_t ok = s.r_ok[k] & mask32(o_g <= alpha_max);
        const T v_alpha_all = s.r_tf[k] * s.r_dot[k] - vt[k] / s.r_om[k];
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
    T* dst = a.pair_grad + j * S;
    for (int q = 0; q < S; ++q) {
      T* l = s.lanes.data() + size_t(q) * kTileSize;
      dst[q] = lane_sum(l, nx);
      std::fill(l, l + nx, T(0));
    }
  }
}

// The instantiations the dispatcher picks from.
void backward_tile_base(const BwdArgs<float>& a, int64_t t, BwdScratch<float>& s) {
  backward_tile(a, t, s);
}
#if COBGS_AVX2_CLONES
COBGS_TARGET_AVX2 void backward_tile_avx2(const BwdArgs<float>& a, int64_t t,
                                          BwdScratch<float>& s) {
  backward_tile(a, t, s);
}
#endif
void backward_tile_base(const BwdArgs<double>& a, int64_t t, BwdScratch<double>& s) {
  backward_tile(a, t, s);
}

template <typename T>
using BackwardTileFn = void (*)(const BwdArgs<T>&, int64_t, BwdScratch<T>&);

inline BackwardTileFn<float> pick_backward_tile(float) {
#if COBGS_AVX2_CLONES
  if (cpu_use_avx2()) return &backward_tile_avx2;
#endif
  return static_cast<BackwardTileFn<float>>(&backward_tile_base);
}
inline BackwardTileFn<double> pick_backward_tile(double) {
  return static_cast<BackwardTileFn<double>>(&backward_tile_base);
}

template <typename T>
void blend_backward(const at::Tensor& means2d, const at::Tensor& conics,
                    const at::Tensor& opacities, const at::Tensor& features,
                    const at::Tensor& background, const at::Tensor& tile_offsets,
                    const at::Tensor& flat_ids, const at::Tensor& transmittance,
                    const at::Tensor& n_contrib, const at::Tensor& v_image,
                    const at::Tensor& v_trans, at::Tensor& v_means2d, at::Tensor& v_conics,
                    at::Tensor& v_opacities, at::Tensor& v_features, at::Tensor& v_background) {
  const int64_t n = means2d.size(0);
  const int64_t m = flat_ids.numel();
  const int C = static_cast<int>(features.size(1));
  const int S = kFeat + C;  // gradient slots per tile-list entry
  const int width = static_cast<int>(transmittance.size(1));
  const int height = static_cast<int>(transmittance.size(0));
  const int tiles_x = (width + kTileSize - 1) / kTileSize;
  const int64_t n_tiles = int64_t(tiles_x) * ((height + kTileSize - 1) / kTileSize);
  GaussPrep<T>* prep = reusable_buffer<GaussPrep<T>, 0>(n);  // filled in the region
  const T* m2_ptr = means2d.data_ptr<T>();
  const T* conic_ptr = conics.data_ptr<T>();
  const T* opacity_ptr = opacities.data_ptr<T>();
  // One slot per tile-list entry, written only by the thread owning the tile (no atomics)
  // and reduced per Gaussian afterwards in list order (deterministic).
  T* pair_grad = reusable_buffer<T, 4>(size_t(m) * S);  // zeroed tile by tile

  BwdArgs<T> a;
  a.prep = prep;
  a.off = tile_offsets.data_ptr<int64_t>();
  a.ids = flat_ids.data_ptr<int32_t>();
  a.feat = features.data_ptr<T>();
  a.bg = background.data_ptr<T>();
  a.trans = transmittance.data_ptr<T>();
  a.n_contrib = n_contrib.data_ptr<int32_t>();
  a.v_image = v_image.data_ptr<T>();
  a.v_trans = v_trans.data_ptr<T>();
  a.C = C;
  a.S = S;
  a.width = width;
  a.height = height;
  a.tiles_x = tiles_x;
  a.pair_grad = pair_grad;
  const BackwardTileFn<T> tile_fn = pick_backward_tile(T(0));

#pragma omp parallel num_threads(cpu_threads())
  {
    prepare<T>(m2_ptr, conic_ptr, opacity_ptr, n, prep);  // ends with a barrier
    std::unique_ptr<BwdScratch<T>> scratch(new BwdScratch<T>(C, S));
#pragma omp for schedule(dynamic, 1)
    for (int64_t tile = 0; tile < n_tiles; ++tile) tile_fn(a, tile, *scratch);
  }

  // Fixed-order reduction of the per-entry gradients into per-Gaussian gradients.
  const int32_t* ids = a.ids;
  const T* tr = a.trans;
  const T* vimg = a.v_image;
  T* vm = v_means2d.data_ptr<T>();
  T* vco = v_conics.data_ptr<T>();
  T* vo = v_opacities.data_ptr<T>();
  T* vf = v_features.data_ptr<T>();
  for (int64_t j = 0; j < m; ++j) {
    const int64_t g = ids[j];
    const T* src = pair_grad + j * S;
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
