// CUDA forward of the `blend` op (see blend.h and blend_cuda.cuh): one block per tile, one
// thread per pixel, front to back through the tile's list in batches staged in shared
// memory. Every per-pixel decision and sum is the CPU kernel's, in its operation order
// (built with --fmad=false), so image, transmittance, n_contrib and the label counts equal
// the CPU op's; label weights are summed with atomics (order-dependent rounding only).
// Label statistics are aggregated per warp (one atomic per label and warp) before they
// reach memory.
#include <torch/library.h>

#include "blend_cuda.cuh"

namespace cobgs {
namespace {

using namespace blend_detail;
using cuda::kFullMask;

template <typename T>
struct FwdParams {
  const GaussPrep<T>* prep;
  const int64_t* off;
  const int32_t* ids;
  const T* feat;           // [N, C]
  const T* bg;             // [C]
  const int32_t* labels;   // [H, W] or null
  int C, K, width, height, tiles_x;
  int64_t n, m, n_tiles;   // Gaussians, list entries, tiles
  int* error;              // InputErrors found
  T* img;                  // [H, W, C]
  T* trans;                // [H, W]
  int32_t* n_contrib;      // [H, W]
  int32_t* counts;         // [N, K]
  T* weights;              // [N, K] (summed in T, converted to float32 after)
};

// NC > 0: a fixed channel count (colour in registers, features staged in shared memory);
// NC = 0: any count (colour accumulated in the output image, features read from memory).
template <typename T, int NC, bool kLabels, bool kFast>
__global__ void __launch_bounds__(kBlock) blend_fwd_kernel(const FwdParams<T> p) {
  constexpr int kRegC = NC > 0 ? NC : 1;
  __shared__ GaussPrep<T> recs[kBlock];
  __shared__ int32_t rec_id[kBlock];
  __shared__ T rec_f[kRegC][kBlock];
  const int64_t tile = blockIdx.x;
  const TilePixel px = tile_pixel(tile, p.tiles_x, p.width, p.height);
  const int C = NC > 0 ? NC : p.C;
  int64_t lo, hi;
  tile_list(p.off, tile, p.n_tiles, p.m, p.error, lo, hi);
  const T xc = T(px.x) + T(0.5), yc = T(px.y) + T(0.5);
  T Tp = T(1);
  T col[kRegC];
  for (int c = 0; c < kRegC; ++c) col[c] = T(0);
  T* img = p.img + px.index * C;
  if (NC == 0 && px.inside)
    for (int c = 0; c < C; ++c) img[c] = T(0);
  int32_t last = 0;
  bool done = !px.inside;
  int lab = kLabels && px.inside ? p.labels[px.index] : -1;
  if (lab < -1 || lab >= p.K) {
    atomicOr(p.error, kBadLabels);
    lab = -1;
  }
  const int lane = threadIdx.x % 32;

  for (int64_t base = lo; base < hi; base += kBlock) {
    // (also the barrier before the batch's records are overwritten)
    if (__syncthreads_count(done) == kBlock) break;
    const int64_t j = base + threadIdx.x;
    if (j < hi) {
      const int32_t g = load_entry(p.ids, j, p.n, p.prep, recs[threadIdx.x], p.error);
      rec_id[threadIdx.x] = g;
      if (NC > 0)
        for (int c = 0; c < kRegC; ++c)
          rec_f[c][threadIdx.x] = g >= 0 ? p.feat[int64_t(g) * NC + c] : T(0);
    }
    __syncthreads();
    const int nb = static_cast<int>(hi - base < kBlock ? hi - base : kBlock);
    for (int k = 0; k < nb; ++k) {
      bool blended = false;
      T w = T(0);
      if (!done && in_box(recs[k], px.x, px.y)) {
        const GaussPrep<T>& g = recs[k];
        const T power = path_power<kFast>(g, xc - g.mx, yc - g.my);
        if (power <= T(0) && power >= g.power_reject) {
          T alpha = g.o * path_exp<kFast>(power);
          alpha = alpha < T(math::kAlphaMax) ? alpha : T(math::kAlphaMax);
          if (alpha >= T(math::kAlphaMin)) {
            const T test_t = Tp * (T(1) - alpha);
            if (test_t < T(math::kTransmittanceMin)) {
              done = true;  // this Gaussian is not blended; the pixel stops
            } else {
              w = alpha * Tp;
              if (NC > 0) {
                for (int c = 0; c < kRegC; ++c)
                  col[c] = kFast ? fma(rec_f[c][k], w, col[c]) : col[c] + rec_f[c][k] * w;
              } else {
                const T* f = p.feat + int64_t(rec_id[k]) * C;
                for (int c = 0; c < C; ++c) img[c] = kFast ? fma(f[c], w, img[c]) : img[c] + f[c] * w;
              }
              Tp = test_t;
              last = static_cast<int32_t>(base + k - lo + 1);
              blended = true;
            }
          }
        }
      }
      if (kLabels) {
        // One count and one weight sum per label present among the warp's blended pixels.
        unsigned pending = __ballot_sync(kFullMask, blended && lab >= 0);
        while (pending) {
          const int l = __shfl_sync(kFullMask, lab, __ffs(pending) - 1);
          const bool mine = blended && lab == l;
          const unsigned m = __ballot_sync(kFullMask, mine);
          const T ws = cuda::warp_sum(mine ? w : T(0));
          if (lane == 0) {
            const int64_t slot = int64_t(rec_id[k]) * p.K + l;
            atomicAdd(p.counts + slot, __popc(m));
            atomicAdd(p.weights + slot, ws);
          }
          pending &= ~m;
        }
      }
    }
  }
  if (!px.inside) return;
  for (int c = 0; c < C; ++c) {
    const T v = NC > 0 ? col[c < kRegC ? c : 0] : img[c];
    img[c] = v + Tp * p.bg[c];
  }
  p.trans[px.index] = Tp;
  p.n_contrib[px.index] = last;
}

template <typename T, int NC, bool kFast>
void launch_fwd_path(const FwdParams<T>& p, int64_t n_tiles) {
  const unsigned int grid = static_cast<unsigned int>(n_tiles);
  if (p.labels)
    blend_fwd_kernel<T, NC, true, kFast><<<grid, kBlock, 0, cuda::stream()>>>(p);
  else
    blend_fwd_kernel<T, NC, false, kFast><<<grid, kBlock, 0, cuda::stream()>>>(p);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
}

template <typename T, int NC>
void launch_fwd(const FwdParams<T>& p, int64_t n_tiles) {
  if (cuda_fast_path())
    launch_fwd_path<T, NC, true>(p, n_tiles);
  else
    launch_fwd_path<T, NC, false>(p, n_tiles);
}

}  // namespace

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> blend_cuda(
    const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
    const at::Tensor& features, const at::Tensor& background, const at::Tensor& tile_offsets,
    const at::Tensor& flat_ids, int64_t width, int64_t height,
    const std::optional<at::Tensor>& pixel_labels, int64_t num_labels,
    const std::optional<at::Tensor>& prep, bool check) {
  TORCH_CHECK(means2d.is_cuda(), "means2d must be a CUDA tensor, got ", means2d.device());
  const int64_t n_tiles = check_blend_inputs(means2d, conics, opacities, features, background,
                                             tile_offsets, flat_ids, width, height);
  TORCH_CHECK(num_labels >= 1, "num_labels must be >= 1, got ", num_labels);
  const c10::cuda::CUDAGuard guard(means2d.device());
  const int64_t n = means2d.size(0), c = features.size(1);
  const int32_t* labels = nullptr;
  if (pixel_labels.has_value()) {
    check_pixel_labels(means2d, *pixel_labels, width, height);
    labels = pixel_labels->data_ptr<int32_t>();  // values checked by the kernel
  }
  at::Tensor error = at::zeros({1}, means2d.options().dtype(at::kInt));
  const auto opts = means2d.options();
  at::Tensor image = at::empty({height, width, c}, opts);
  at::Tensor trans = at::empty({height, width}, opts);
  at::Tensor n_contrib = at::empty({height, width}, opts.dtype(at::kInt));
  const int64_t rows = labels ? n : 0;
  at::Tensor label_counts = at::zeros({rows, num_labels}, opts.dtype(at::kInt));
  at::Tensor weight_sums = at::zeros({rows, num_labels}, opts);
  at::Tensor storage;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "cobgs::blend_cuda", [&] {
    FwdParams<scalar_t> p;
    p.prep = prep_for_pass<scalar_t>(prep, means2d, conics, opacities, storage);
    p.off = tile_offsets.data_ptr<int64_t>();
    p.ids = flat_ids.data_ptr<int32_t>();
    p.feat = features.data_ptr<scalar_t>();
    p.bg = background.data_ptr<scalar_t>();
    p.labels = labels;
    p.C = static_cast<int>(c);
    p.K = static_cast<int>(num_labels);
    p.width = static_cast<int>(width);
    p.height = static_cast<int>(height);
    p.tiles_x = static_cast<int>((width + math::kTileSize - 1) / math::kTileSize);
    p.img = image.data_ptr<scalar_t>();
    p.trans = trans.data_ptr<scalar_t>();
    p.n_contrib = n_contrib.data_ptr<int32_t>();
    p.counts = label_counts.data_ptr<int32_t>();
    p.weights = weight_sums.data_ptr<scalar_t>();
    p.n = n;
    p.m = flat_ids.numel();
    p.n_tiles = n_tiles;
    p.error = error.data_ptr<int>();
    switch (c) {
      case 1: launch_fwd<scalar_t, 1>(p, n_tiles); break;
      case 2: launch_fwd<scalar_t, 2>(p, n_tiles); break;
      case 3: launch_fwd<scalar_t, 3>(p, n_tiles); break;
      case 4: launch_fwd<scalar_t, 4>(p, n_tiles); break;
      default: launch_fwd<scalar_t, 0>(p, n_tiles); break;
    }
  });
  if (check) raise_input_errors(error, n, num_labels);
  return {image, trans, n_contrib, label_counts, weight_sums.to(at::kFloat)};
}

TORCH_LIBRARY_IMPL(cobgs, CUDA, m) { m.impl("blend", &blend_cuda); }

}  // namespace cobgs
