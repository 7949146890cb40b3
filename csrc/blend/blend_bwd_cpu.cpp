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
  const int64_t* slot;      // entry -> gradient slot (group_entries)
  T* slot_grad;             // [M, S] gradient slots
  uint8_t* slot_hit;        // [M]: 1 when the slot holds gradients, 0 when it is unset
};

// Per-thread state of the tile (structure of arrays, channel-major where per channel).
template <typename T>
struct BwdScratch {
  alignas(64) T Tp[kTilePixels];   // transmittance behind the current Gaussian
  alignas(64) T vtt[kTilePixels];  // dL/dT_final · T_final
  alignas(64) int32_t last[kTilePixels];
  // Phase-1 results of the current entry, per block of its box (at most 32 blocks).
  alignas(64) T blk_gauss[kTilePixels];  // 32 blocks x 8 lanes
  alignas(64) int32_t blk_ok[kTilePixels];
  int blk_pix[kTilePixels / simd::kLanes];  // tile index of the block's first pixel
  std::vector<T> rest;   // R per channel and pixel
  std::vector<T> vcol;   // dL/dimage per channel and pixel
  // Per-lane dL/df sums of the current entry, [C][8], for the kernel with a run-time
  // channel count (fixed counts keep them in registers).
  std::vector<T> acc_f;

  explicit BwdScratch(int C)
      : rest(size_t(kTilePixels) * C), vcol(size_t(kTilePixels) * C),
        acc_f(size_t(C) * simd::kLanes, T(0)) {}
};

template <typename T>
using BackwardTileFn = void (*)(const BwdArgs<T>&, int64_t, BwdScratch<T>&);

}  // namespace

// The kernel once per instruction set (float32; float64 only in the baseline version).
namespace backward_tile_base {
#define COBGS_ISA_LEVEL 0
#include "blend_bwd_tile_cpu.h"
#undef COBGS_ISA_LEVEL
}  // namespace backward_tile_base
#if COBGS_AVX2_CLONES
COBGS_BEGIN_ISA_AVX2
namespace backward_tile_avx2 {
#define COBGS_ISA_LEVEL 1
#include "blend_bwd_tile_cpu.h"
#undef COBGS_ISA_LEVEL
}  // namespace backward_tile_avx2
COBGS_END_ISA
COBGS_BEGIN_ISA_AVX512
namespace backward_tile_avx512 {
#define COBGS_ISA_LEVEL 2
#include "blend_bwd_tile_cpu.h"
#undef COBGS_ISA_LEVEL
}  // namespace backward_tile_avx512
COBGS_END_ISA
// The fast path (cpu_isa.h): the same kernel with fused multiply-adds.
COBGS_BEGIN_ISA_AVX2_FAST
namespace backward_tile_avx2fast {
#define COBGS_ISA_LEVEL 1
#include "blend_bwd_tile_cpu.h"
#undef COBGS_ISA_LEVEL
}  // namespace backward_tile_avx2fast
COBGS_END_ISA
COBGS_BEGIN_ISA_AVX512_FAST
namespace backward_tile_avx512fast {
#define COBGS_ISA_LEVEL 2
#include "blend_bwd_tile_cpu.h"
#undef COBGS_ISA_LEVEL
}  // namespace backward_tile_avx512fast
COBGS_END_ISA
#endif

namespace {

inline BackwardTileFn<float> pick_backward_tile(float, int channels) {
  return COBGS_ISA_DISPATCH_FAST(backward_tile, pick<float>(channels));
}
inline BackwardTileFn<double> pick_backward_tile(double, int) {
  return backward_tile_base::backward_tile<double, 0>;
}

template <typename T>
void blend_backward(const at::Tensor& means2d, const at::Tensor& conics,
                    const at::Tensor& opacities, const at::Tensor& features,
                    const at::Tensor& background, const at::Tensor& tile_offsets,
                    const at::Tensor& flat_ids, const at::Tensor& transmittance,
                    const at::Tensor& n_contrib, const at::Tensor& v_image,
                    const at::Tensor& v_trans, const GaussPrep<T>* given,
                    at::Tensor& v_means2d, at::Tensor& v_conics, at::Tensor& v_opacities,
                    at::Tensor& v_features, at::Tensor& v_background) {
  const int64_t n = means2d.size(0);
  const int64_t m = flat_ids.numel();
  const int C = static_cast<int>(features.size(1));
  const int S = kFeat + C;  // gradient slots per tile-list entry
  const int width = static_cast<int>(transmittance.size(1));
  const int height = static_cast<int>(transmittance.size(0));
  const int tiles_x = (width + kTileSize - 1) / kTileSize;
  const int64_t n_tiles = int64_t(tiles_x) * ((height + kTileSize - 1) / kTileSize);
  // Filled in the region unless the caller passed the records.
  GaussPrep<T>* prep = given ? nullptr : reusable_buffer<GaussPrep<T>, 0>(n);
  const T* m2_ptr = means2d.data_ptr<T>();
  const T* conic_ptr = conics.data_ptr<T>();
  const T* opacity_ptr = opacities.data_ptr<T>();
  // One slot per tile-list entry, written only by the thread owning the tile (no atomics),
  // entries grouped by Gaussian; reduced per Gaussian in list order (deterministic).
  T* slot_grad = reusable_buffer<T, 4>(size_t(m) * S);  // slots with slot_hit set are written
  uint8_t* slot_hit = reusable_buffer<uint8_t, 5>(size_t(m));  // every entry written
  const EntrySlots slots = EntrySlots::buffers(m, n);
  const int64_t* order = tile_order(tile_offsets.data_ptr<int64_t>(), n_tiles);
  // Per tile: how many entries of its list the pass visits (the largest n_contrib), which
  // must lie within the list (a check that also guards the tile kernel's indexing).
  int32_t* live = reusable_buffer<int32_t, 6>(size_t(n_tiles));
  {
    const int32_t* nc = n_contrib.data_ptr<int32_t>();
    const int64_t* off = tile_offsets.data_ptr<int64_t>();
    bool ok = true;
    for (int64_t t = 0; t < n_tiles; ++t) {
      const int tx0 = int(t % tiles_x) * kTileSize, ty0 = int(t / tiles_x) * kTileSize;
      const int tx1 = std::min(tx0 + kTileSize, width), ty1 = std::min(ty0 + kTileSize, height);
      int32_t mx = 0;
      for (int py = ty0; py < ty1; ++py)
        for (int px = tx0; px < tx1; ++px) {
          const int32_t v = nc[int64_t(py) * width + px];
          ok &= v >= 0;
          mx = std::max(mx, v);
        }
      ok &= mx <= off[t + 1] - off[t];
      live[t] = mx;
    }
    TORCH_CHECK(ok, "n_contrib must lie in 0 .. the length of the pixel's tile list "
                "(the n_contrib output of the forward pass with the same tile lists)");
  }

  BwdArgs<T> a;
  a.prep = given ? given : prep;
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
  a.slot = slots.slot;
  a.slot_grad = slot_grad;
  a.slot_hit = slot_hit;
  const BackwardTileFn<T> tile_fn = pick_backward_tile(T(0), C);
  T* vm = v_means2d.data_ptr<T>();
  T* vco = v_conics.data_ptr<T>();
  T* vo = v_opacities.data_ptr<T>();
  T* vf = v_features.data_ptr<T>();

  COBGS_PROF_COUNT(kCallsBwd, 1);
#pragma omp parallel num_threads(cpu_threads())
  {
    if (!given) {
      COBGS_PROF_SCOPE(kBwdPrepare);
      prepare<T>(m2_ptr, conic_ptr, opacity_ptr, n, prep);  // ends with a barrier
    }
    {
      COBGS_PROF_SCOPE(kBwdGroup);
      group_live_entries(a.ids, a.off, n_tiles, live, n, slots);  // ends with a barrier
    }
    BwdScratch<T> scratch(C);  // on the stack: its alignas holds
    {
      COBGS_PROF_SCOPE(kBwdTiles);
#pragma omp for schedule(dynamic, 1)
      for (int64_t k = 0; k < n_tiles; ++k) tile_fn(a, order[k], scratch);
    }
    // Per Gaussian: the sum of its entries' gradients in list order.
    COBGS_PROF_SCOPE(kBwdReduce);
    std::vector<T> sum(S);
#pragma omp for schedule(static)
    for (int64_t g = 0; g < n; ++g) {
      std::fill(sum.begin(), sum.end(), T(0));
      for (int64_t e = slots.start[g]; e < slots.start[g + 1]; ++e) {
        if (!slot_hit[e]) continue;  // the entry contributed nothing: its slot is unset
        const T* src = slot_grad + e * S;
        for (int q = 0; q < S; ++q) sum[q] += src[q];
      }
      vm[2 * g] = sum[kMx];
      vm[2 * g + 1] = sum[kMy];
      vco[3 * g] = sum[kCa];
      vco[3 * g + 1] = sum[kCb];
      vco[3 * g + 2] = sum[kCc];
      vo[g] = sum[kOp];
      for (int c = 0; c < C; ++c) vf[g * C + c] = sum[kFeat + c];
    }
  }

  const T* tr = a.trans;
  const T* vimg = a.v_image;
  // image = ... + T_final · background.
  COBGS_PROF_SCOPE(kBwdBackground);
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
    const at::Tensor& v_image, const at::Tensor& v_transmittance,
    const std::optional<at::Tensor>& prep, bool /*check: the CPU always checks*/) {
  COBGS_CHECK_CPU(means2d);
  check_blend_bwd_inputs(means2d, conics, opacities, features, background, tile_offsets,
                         flat_ids, transmittance, n_contrib, v_image, v_transmittance);
  check_tile_lists_cpu(tile_offsets, flat_ids, means2d.size(0));
  // Every entry is written by blend_backward.
  at::Tensor v_means2d = at::empty_like(means2d);
  at::Tensor v_conics = at::empty_like(conics);
  at::Tensor v_opacities = at::empty_like(opacities);
  at::Tensor v_features = at::empty_like(features);
  at::Tensor v_background = at::empty_like(background);
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "cobgs::blend_bwd", [&] {
    blend_backward<scalar_t>(means2d, conics, opacities, features, background, tile_offsets,
                             flat_ids, transmittance, n_contrib, v_image, v_transmittance,
                             given_prep<scalar_t>(prep, means2d), v_means2d, v_conics,
                             v_opacities, v_features, v_background);
  });
  return {v_means2d, v_conics, v_opacities, v_features, v_background};
}

TORCH_LIBRARY_IMPL(cobgs, CPU, m) { m.impl("blend_bwd", &blend_bwd_cpu); }

}  // namespace cobgs
