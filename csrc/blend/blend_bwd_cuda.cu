// CUDA backward of the `blend` op (see blend.h and blend_bwd_cpu.cpp for the formulas):
// one block per tile, one thread per pixel, walking the tile's list back to front from
// the block's largest n_contrib, in batches staged in shared memory. Per pixel the
// recomputed decisions (which pixels each Gaussian was blended into, where the 0.99 clamp
// holds) are the forward's and the CPU's bit for bit (built with --fmad=false; float32
// takes the hardware exp away from the thresholds, see exact_near_thresholds); the
// gradient arithmetic after them uses explicit fused multiply-adds. The per-pixel gradient terms of a Gaussian are
// summed over each warp (shuffles) and added to its gradient with one atomic per warp and
// value, so the gradients agree with the CPU op up to rounding.
#include <torch/library.h>

#include "blend_cuda.cuh"

namespace cobgs {
namespace {

using namespace blend_detail;
using cuda::kFullMask;

template <typename T>
struct BwdParams {
  const GaussPrep<T>* prep;
  const int64_t* off;
  const int32_t* ids;
  const T* feat;            // [N, C]
  const T* bg;              // [C]
  const T* trans;           // [H, W] T_final
  const int32_t* n_contrib; // [H, W]
  const T* v_image;         // [H, W, C]
  const T* v_trans;         // [H, W]
  int C, width, height, tiles_x;
  int64_t n, m, n_tiles;    // Gaussians, list entries, tiles
  T* rest;                  // [H, W, C] scratch for NC = 0: colour behind, per channel
  T* v_means2d;             // [N, 2]  (zero-filled; atomics add into them)
  T* v_conics;              // [N, 3]
  T* v_opacities;           // [N]
  T* v_features;            // [N, C]
  int* error;               // InputErrors found
};

__device__ __forceinline__ float reciprocal(float x) { return __frcp_rn(x); }
__device__ __forceinline__ double reciprocal(double x) { return 1.0 / x; }

// G = exp(power) and o·G for the gradients. float32: the hardware exp (relative error
// < 5e-7 here, |power| < 88), except where o·G lies within 1e-5 (relative) of 1/255 or
// 0.99, where the decisions "blended" (α >= 1/255) and "clamped" (o·G > 0.99) hang on the
// last bits: there the shared exact exp (gs_math.h) decides, as in the forward and on the
// CPU. float64: the exact one throughout.
__device__ __forceinline__ void exact_near_thresholds(float power, float o, float& gauss,
                                                      float& o_g) {
  gauss = __expf(power);
  o_g = o * gauss;
  constexpr float lo = float(math::kAlphaMin), hi = float(math::kAlphaMax);
  if (fabsf(o_g - lo) <= 1e-5f * lo || fabsf(o_g - hi) <= 1e-5f * hi) {
    gauss = math::gauss_exp(power);
    o_g = o * gauss;
  }
}
__device__ __forceinline__ void exact_near_thresholds(double power, double o, double& gauss,
                                                      double& o_g) {
  gauss = math::gauss_exp(power);
  o_g = o * gauss;
}

template <typename T, int NC, bool kFast>
__global__ void __launch_bounds__(kBlock) blend_bwd_kernel(const BwdParams<T> p) {
  constexpr int kRegC = NC > 0 ? NC : 1;
  __shared__ GaussPrep<T> recs[kBlock];
  __shared__ int32_t rec_id[kBlock];
  __shared__ T rec_f[kRegC][kBlock];
  __shared__ int block_last;
  const int64_t tile = blockIdx.x;
  const TilePixel px = tile_pixel(tile, p.tiles_x, p.width, p.height);
  const int C = NC > 0 ? NC : p.C;
  int64_t lo, hi;
  tile_list(p.off, tile, p.n_tiles, p.m, p.error, lo, hi);
  const int lane = threadIdx.x % 32;
  const T xc = T(px.x) + T(0.5), yc = T(px.y) + T(0.5);

  // Per-pixel state: T behind the current Gaussian (starting at T_final), dL/dT_final ·
  // T_final, the pixel's last contributor, and per channel the colour behind (starting
  // at the background) and dL/dC.
  T Tp = T(1), vtt = T(0);
  int last = 0;
  T rest[kRegC], vcol[kRegC];
  for (int c = 0; c < kRegC; ++c) rest[c] = vcol[c] = T(0);
  T* rest_g = p.rest + px.index * C;  // NC = 0 only
  const T* vimg = p.v_image + px.index * C;
  if (px.inside) {
    const T tf = p.trans[px.index];
    Tp = tf;
    vtt = p.v_trans[px.index] * tf;
    last = p.n_contrib[px.index];
    if (last < 0 || last > hi - lo) {
      atomicOr(p.error, kBadNContrib);
      last = 0;
    }
    if (NC > 0) {
      for (int c = 0; c < kRegC; ++c) {
        rest[c] = p.bg[c];
        vcol[c] = vimg[c];
      }
    } else {
      for (int c = 0; c < C; ++c) rest_g[c] = p.bg[c];
    }
  }
  if (threadIdx.x == 0) block_last = 0;
  __syncthreads();
  const int warp_last = cuda::warp_max_all(last);
  if (lane == 0) atomicMax(&block_last, warp_last);
  __syncthreads();
  const int max_last = block_last;

  for (int top = max_last; top > 0; top -= kBlock) {
    const int bottom = top > kBlock ? top - kBlock : 0;
    __syncthreads();  // everyone is done with the previous batch
    const int r = bottom + int(threadIdx.x);
    if (r < top) {
      const int32_t g = load_entry(p.ids, lo + r, p.n, p.prep, recs[threadIdx.x], p.error);
      rec_id[threadIdx.x] = g;
      if (NC > 0)
        for (int c = 0; c < kRegC; ++c)
          rec_f[c][threadIdx.x] = g >= 0 ? p.feat[int64_t(g) * NC + c] : T(0);
    }
    __syncthreads();
    for (int k = top - bottom - 1; k >= 0; --k) {
      const GaussPrep<T>& g = recs[k];
      bool ok = false;
      T at = T(0);  // α · T in front of the Gaussian (the weight of dL/df)
      T v_mx = T(0), v_my = T(0), v_ca = T(0), v_cb = T(0), v_cc = T(0), v_op = T(0);
      if (bottom + k < last && in_box(g, px.x, px.y)) {
        const T dx = xc - g.mx, dy = yc - g.my;
        const T power = path_power<kFast>(g, dx, dy);
        if (power <= T(0) && power >= g.power_reject) {
          T gauss, o_g;
          if (kFast) {  // the forward's fast formulas: the same decisions as the fast forward
            gauss = fast_exp(power);
            o_g = g.o * gauss;
          } else {
            exact_near_thresholds(power, g.o, gauss, o_g);
          }
          const T alpha = o_g < T(math::kAlphaMax) ? o_g : T(math::kAlphaMax);
          if (alpha >= T(math::kAlphaMin)) {  // the forward blended it here
            ok = true;
            // From here on only gradient values: fused multiply-adds and the rounded
            // reciprocal (the decisions above are the forward's, bit for bit).
            const T one_minus = T(1) - alpha;
            const T inv_om = reciprocal(one_minus);
            const T t_front = Tp * inv_om;
            Tp = t_front;
            at = alpha * t_front;
            // Σ_c (f_c - R_c) dL/dC_c, then R ← α f + (1 - α) R.
            T dot = T(0);
            if (NC > 0) {
              for (int c = 0; c < kRegC; ++c) {
                const T fc = rec_f[c][k];
                dot = fma(fc - rest[c], vcol[c], dot);
                rest[c] = fma(alpha, fc, one_minus * rest[c]);
              }
            } else {
              const T* f = p.feat + int64_t(rec_id[k]) * C;
              for (int c = 0; c < C; ++c) {
                const T fc = f[c], rv = rest_g[c];
                dot = fma(fc - rv, vimg[c], dot);
                rest_g[c] = fma(alpha, fc, one_minus * rv);
              }
            }
            // dL/dα (none where the 0.99 clamp is active) → opacity, conic, mean.
            const T v_alpha =
                o_g <= T(math::kAlphaMax) ? fma(t_front, dot, -vtt * inv_om) : T(0);
            const T v_power = o_g * v_alpha;
            v_op = gauss * v_alpha;
            const T hp = T(-0.5) * v_power;
            v_ca = hp * dx * dx;
            v_cb = -dx * dy * v_power;
            v_cc = hp * dy * dy;
            // d = pixel - mean: d(power)/d(mean) = -d(power)/d(d).
            v_mx = fma(g.ca, dx, g.cb * dy) * v_power;
            v_my = fma(g.cb, dx, g.cc * dy) * v_power;
          }
        }
      }
      if (!__any_sync(kFullMask, ok)) continue;  // warp-uniform
      const int64_t gi = rec_id[k];
      v_mx = cuda::warp_sum(v_mx);
      v_my = cuda::warp_sum(v_my);
      v_ca = cuda::warp_sum(v_ca);
      v_cb = cuda::warp_sum(v_cb);
      v_cc = cuda::warp_sum(v_cc);
      v_op = cuda::warp_sum(v_op);
      if (lane == 0) {
        atomicAdd(p.v_means2d + 2 * gi, v_mx);
        atomicAdd(p.v_means2d + 2 * gi + 1, v_my);
        atomicAdd(p.v_conics + 3 * gi, v_ca);
        atomicAdd(p.v_conics + 3 * gi + 1, v_cb);
        atomicAdd(p.v_conics + 3 * gi + 2, v_cc);
        atomicAdd(p.v_opacities + gi, v_op);
      }
      for (int c = 0; c < C; ++c) {
        const T vc = NC > 0 ? vcol[c < kRegC ? c : 0] : (px.inside ? vimg[c] : T(0));
        const T vf = cuda::warp_sum(ok ? at * vc : T(0));
        if (lane == 0) atomicAdd(p.v_features + gi * C + c, vf);
      }
    }
  }
}

template <typename T, int NC>
void launch_bwd(const BwdParams<T>& p, int64_t n_tiles) {
  const unsigned int grid = static_cast<unsigned int>(n_tiles);
  if (cuda_fast_path())
    blend_bwd_kernel<T, NC, true><<<grid, kBlock, 0, cuda::stream()>>>(p);
  else
    blend_bwd_kernel<T, NC, false><<<grid, kBlock, 0, cuda::stream()>>>(p);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
}

}  // namespace

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> blend_bwd_cuda(
    const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
    const at::Tensor& features, const at::Tensor& background, const at::Tensor& tile_offsets,
    const at::Tensor& flat_ids, const at::Tensor& transmittance, const at::Tensor& n_contrib,
    const at::Tensor& v_image, const at::Tensor& v_transmittance,
    const std::optional<at::Tensor>& prep, bool check) {
  TORCH_CHECK(means2d.is_cuda(), "means2d must be a CUDA tensor, got ", means2d.device());
  const std::pair<int64_t, int64_t> size = check_blend_bwd_inputs(
      means2d, conics, opacities, features, background, tile_offsets, flat_ids, transmittance,
      n_contrib, v_image, v_transmittance);
  const int64_t height = size.first, width = size.second;
  const c10::cuda::CUDAGuard guard(means2d.device());
  const int64_t c = features.size(1);
  const int tiles_x = static_cast<int>((width + math::kTileSize - 1) / math::kTileSize);
  const int64_t n_tiles = int64_t(tiles_x) * ((height + math::kTileSize - 1) / math::kTileSize);
  at::Tensor v_means2d = at::zeros_like(means2d);
  at::Tensor v_conics = at::zeros_like(conics);
  at::Tensor v_opacities = at::zeros_like(opacities);
  at::Tensor v_features = at::zeros_like(features);
  at::Tensor error = at::zeros({1}, means2d.options().dtype(at::kInt));
  at::Tensor rest = c > kSharedChannels ? at::empty({height, width, c}, means2d.options())
                                        : at::empty({0}, means2d.options());
  at::Tensor storage;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "cobgs::blend_bwd_cuda", [&] {
    BwdParams<scalar_t> p;
    p.prep = prep_for_pass<scalar_t>(prep, means2d, conics, opacities, storage);
    p.off = tile_offsets.data_ptr<int64_t>();
    p.ids = flat_ids.data_ptr<int32_t>();
    p.feat = features.data_ptr<scalar_t>();
    p.bg = background.data_ptr<scalar_t>();
    p.trans = transmittance.data_ptr<scalar_t>();
    p.n_contrib = n_contrib.data_ptr<int32_t>();
    p.v_image = v_image.data_ptr<scalar_t>();
    p.v_trans = v_transmittance.data_ptr<scalar_t>();
    p.C = static_cast<int>(c);
    p.width = static_cast<int>(width);
    p.height = static_cast<int>(height);
    p.tiles_x = tiles_x;
    p.rest = rest.data_ptr<scalar_t>();
    p.v_means2d = v_means2d.data_ptr<scalar_t>();
    p.v_conics = v_conics.data_ptr<scalar_t>();
    p.v_opacities = v_opacities.data_ptr<scalar_t>();
    p.v_features = v_features.data_ptr<scalar_t>();
    p.error = error.data_ptr<int>();
    p.n = means2d.size(0);
    p.m = flat_ids.numel();
    p.n_tiles = n_tiles;
    switch (c) {
      case 1: launch_bwd<scalar_t, 1>(p, n_tiles); break;
      case 2: launch_bwd<scalar_t, 2>(p, n_tiles); break;
      case 3: launch_bwd<scalar_t, 3>(p, n_tiles); break;
      case 4: launch_bwd<scalar_t, 4>(p, n_tiles); break;
      default: launch_bwd<scalar_t, 0>(p, n_tiles); break;
    }
  });
  if (check) raise_input_errors(error, means2d.size(0), 1);
  // image = ... + T_final · background (summed in double, as the CPU op).
  at::Tensor v_background = (transmittance.unsqueeze(-1) * v_image)
                                .sum(at::IntArrayRef{0, 1}, false, at::kDouble)
                                .to(means2d.scalar_type());
  return {v_means2d, v_conics, v_opacities, v_features, v_background};
}

TORCH_LIBRARY_IMPL(cobgs, CUDA, m) { m.impl("blend_bwd", &blend_bwd_cuda); }

}  // namespace cobgs
