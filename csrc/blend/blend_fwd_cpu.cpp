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
  const int64_t* slot;     // entry -> slot of its label statistics (group_entries)
  int32_t* slot_counts;    // [M, K] label statistics per slot
  T* slot_weights;         // [M, K]
};

// Up to this many labels, the label statistics are summed in lane vectors; more labels
// take a per-lane path.
constexpr int kLaneLabels = 4;

// Per-thread state of the tile being rendered: structure of arrays, one 8-pixel block of
// a tile row per vector.
template <typename T>
struct FwdScratch {
  alignas(64) T Tp[kTilePixels];
  alignas(64) int32_t last[kTilePixels];
  alignas(64) int32_t done[kTilePixels];         // -1 once the pixel stopped or outside
  alignas(64) int32_t tile_labels[kTilePixels];  // -1 outside the image
  // Phase-1 results of the current entry, per block of its box (at most 32 blocks).
  alignas(64) T blk_alpha[kTilePixels];  // 32 blocks x 8 lanes
  alignas(64) int32_t blk_cand[kTilePixels];
  int blk_pix[kTilePixels / simd::kLanes];  // tile index of the block's first pixel
  std::vector<T> colour;  // channel-major [C][256]

  explicit FwdScratch(int C) : colour(size_t(kTilePixels) * C) {}
};

template <typename T>
using ForwardTileFn = void (*)(const FwdArgs<T>&, int64_t, FwdScratch<T>&);

}  // namespace

// The kernel once per instruction set (float32; float64 only in the baseline version).
namespace forward_tile_base {
#define COBGS_ISA_LEVEL 0
#include "blend_fwd_tile_cpu.h"
#undef COBGS_ISA_LEVEL
}  // namespace forward_tile_base
#if COBGS_AVX2_CLONES
COBGS_BEGIN_ISA_AVX2
namespace forward_tile_avx2 {
#define COBGS_ISA_LEVEL 1
#include "blend_fwd_tile_cpu.h"
#undef COBGS_ISA_LEVEL
}  // namespace forward_tile_avx2
COBGS_END_ISA
COBGS_BEGIN_ISA_AVX512
namespace forward_tile_avx512 {
#define COBGS_ISA_LEVEL 2
#include "blend_fwd_tile_cpu.h"
#undef COBGS_ISA_LEVEL
}  // namespace forward_tile_avx512
COBGS_END_ISA
// The fast path (cpu_isa.h): the same kernel with fused multiply-adds.
COBGS_BEGIN_ISA_AVX2_FAST
namespace forward_tile_avx2fast {
#define COBGS_ISA_LEVEL 1
#include "blend_fwd_tile_cpu.h"
#undef COBGS_ISA_LEVEL
}  // namespace forward_tile_avx2fast
COBGS_END_ISA
COBGS_BEGIN_ISA_AVX512_FAST
namespace forward_tile_avx512fast {
#define COBGS_ISA_LEVEL 2
#include "blend_fwd_tile_cpu.h"
#undef COBGS_ISA_LEVEL
}  // namespace forward_tile_avx512fast
COBGS_END_ISA
#endif

namespace {

inline ForwardTileFn<float> pick_forward_tile(float, int channels) {
  return COBGS_ISA_DISPATCH_FAST(forward_tile, pick<float>(channels));
}
inline ForwardTileFn<double> pick_forward_tile(double, int) {
  return forward_tile_base::forward_tile<double, 0>;
}

template <typename T>
void blend_forward(const at::Tensor& means2d, const at::Tensor& conics,
                   const at::Tensor& opacities, const at::Tensor& features,
                   const at::Tensor& background, const at::Tensor& tile_offsets,
                   const at::Tensor& flat_ids, int width, int height, const int32_t* labels,
                   int num_labels, const GaussPrep<T>* given, at::Tensor& image,
                   at::Tensor& trans, at::Tensor& n_contrib, at::Tensor& label_counts,
                   at::Tensor& label_weights) {
  const int64_t n = means2d.size(0);
  const int64_t m = flat_ids.numel();
  const int C = static_cast<int>(features.size(1));
  const int K = num_labels;
  const int tiles_x = (width + kTileSize - 1) / kTileSize;
  const int64_t n_tiles = int64_t(tiles_x) * ((height + kTileSize - 1) / kTileSize);
  // Filled in the region unless the caller passed the records.
  GaussPrep<T>* prep = given ? nullptr : reusable_buffer<GaussPrep<T>, 0>(n);
  const T* m2_ptr = means2d.data_ptr<T>();
  const T* conic_ptr = conics.data_ptr<T>();
  const T* opacity_ptr = opacities.data_ptr<T>();
  // Label statistics per tile-list entry, each written only by the thread owning its
  // tile, to the entry's slot (entries grouped by Gaussian), then summed per Gaussian in
  // list order: no atomics, deterministic.
  const size_t pairs = labels ? size_t(m) * K : 0;
  int32_t* slot_counts = reusable_buffer<int32_t, 1>(pairs);
  T* slot_weights = reusable_buffer<T, 2>(pairs);
  const EntrySlots slots = labels ? EntrySlots::buffers(m, n) : EntrySlots{};
  const int64_t* order = tile_order(tile_offsets.data_ptr<int64_t>(), n_tiles);

  FwdArgs<T> a;
  a.prep = given ? given : prep;
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
  a.slot = slots.slot;
  a.slot_counts = slot_counts;
  a.slot_weights = slot_weights;
  const ForwardTileFn<T> tile_fn = pick_forward_tile(T(0), C);
  int32_t* cnt = labels ? label_counts.data_ptr<int32_t>() : nullptr;
  float* wts = labels ? label_weights.data_ptr<float>() : nullptr;

  COBGS_PROF_COUNT(kCallsFwd, 1);
#pragma omp parallel num_threads(cpu_threads())
  {
    if (!given) {
      COBGS_PROF_SCOPE(kFwdPrepare);
      prepare<T>(m2_ptr, conic_ptr, opacity_ptr, n, prep);  // ends with a barrier
    }
    if (labels) {
      group_entries(a.ids, m, n, slots);  // ends with a barrier
#pragma omp for schedule(static)
      for (int64_t i = 0; i < static_cast<int64_t>(pairs); ++i) {
        slot_counts[i] = 0;
        slot_weights[i] = T(0);
      }
    }
    FwdScratch<T> scratch(C);  // on the stack: its alignas holds
    {
      COBGS_PROF_SCOPE(kFwdTiles);
#pragma omp for schedule(dynamic, 1)
      for (int64_t k = 0; k < n_tiles; ++k) tile_fn(a, order[k], scratch);
    }
    if (labels) {
      COBGS_PROF_SCOPE(kFwdLabels);
      // Per Gaussian: its slots in list order.
#pragma omp for schedule(static)
      for (int64_t g = 0; g < n; ++g) {
        for (int l = 0; l < K; ++l) {
          int32_t c = 0;
          T w = T(0);
          for (int64_t e = slots.start[g]; e < slots.start[g + 1]; ++e) {
            c += slot_counts[e * K + l];
            w += slot_weights[e * K + l];
          }
          cnt[g * K + l] = c;
          wts[g * K + l] = static_cast<float>(w);
        }
      }
    }
  }
}

}  // namespace

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> blend_cpu(
    const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
    const at::Tensor& features, const at::Tensor& background, const at::Tensor& tile_offsets,
    const at::Tensor& flat_ids, int64_t width, int64_t height,
    const std::optional<at::Tensor>& pixel_labels, int64_t num_labels,
    const std::optional<at::Tensor>& prep, bool /*check: the CPU always checks*/) {
  COBGS_CHECK_CPU(means2d);
  check_blend_inputs(means2d, conics, opacities, features, background, tile_offsets,
                     flat_ids, width, height);
  check_tile_lists_cpu(tile_offsets, flat_ids, means2d.size(0));
  TORCH_CHECK(num_labels >= 1, "num_labels must be >= 1, got ", num_labels);
  const int64_t n = means2d.size(0), c = features.size(1);
  const int32_t* labels = nullptr;
  if (pixel_labels.has_value()) {
    const at::Tensor& pl = *pixel_labels;
    check_pixel_labels(means2d, pl, width, height);
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
                            labels, static_cast<int>(num_labels), given_prep<scalar_t>(prep, means2d),
                            image, trans, n_contrib, label_counts, label_weights);
  });
  return {image, trans, n_contrib, label_counts, label_weights};
}

TORCH_LIBRARY_IMPL(cobgs, CPU, m) { m.impl("blend", &blend_cpu); }

}  // namespace cobgs
