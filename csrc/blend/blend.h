// Op family `blend`: front-to-back alpha blending of depth-sorted Gaussians per 16x16
// tile, with optional per-label contribution statistics, and its backward pass.
// Per-pixel rule: csrc/common/gs_math.h; contract and oracle: cobgs/render/reference.py
// (blend_reference).
#pragma once

#include <torch/types.h>

#include <optional>
#include <tuple>
#include <utility>

#include "../common/checks.h"
#include "../common/gs_math.h"

namespace cobgs {

// Shapes, dtypes and devices of the inputs both passes share (both backends; the caller
// has checked the device type of means2d). Returns the number of tiles. The contents of
// the tile lists are checked by each backend (check_tile_lists_cpu / _cuda).
inline int64_t check_blend_inputs(const at::Tensor& means2d, const at::Tensor& conics,
                               const at::Tensor& opacities, const at::Tensor& features,
                               const at::Tensor& background, const at::Tensor& tile_offsets,
                               const at::Tensor& flat_ids, int64_t width, int64_t height) {
  COBGS_CHECK_CONTIGUOUS(means2d);
  COBGS_CHECK_LIKE(conics, means2d);
  COBGS_CHECK_LIKE(opacities, means2d);
  COBGS_CHECK_LIKE(features, means2d);
  COBGS_CHECK_LIKE(background, means2d);
  COBGS_CHECK_LIKE(tile_offsets, means2d);
  COBGS_CHECK_LIKE(flat_ids, means2d);
  TORCH_CHECK(means2d.scalar_type() == at::kFloat || means2d.scalar_type() == at::kDouble,
              "means2d must be float32 or float64, got ", means2d.scalar_type());
  TORCH_CHECK(means2d.dim() == 2, "means2d must have shape [N, 2], got ", means2d.sizes());
  TORCH_CHECK(features.dim() == 2, "features must have shape [N, C], got ", features.sizes());
  const int64_t n = means2d.size(0), c = features.size(1);
  TORCH_CHECK(c >= 1, "features must have at least one channel, got ", features.sizes());
  COBGS_CHECK_SHAPE(means2d, n, 2);
  COBGS_CHECK_SHAPE(conics, n, 3);
  COBGS_CHECK_SHAPE(opacities, n);
  COBGS_CHECK_SHAPE(features, n, c);
  COBGS_CHECK_SHAPE(background, c);
  for (const auto* t : {&conics, &opacities, &features, &background})
    COBGS_CHECK_DTYPE((*t), means2d.scalar_type());
  TORCH_CHECK(width > 0 && height > 0, "width and height must be positive, got ", width,
              " x ", height);
  const int64_t tiles = ((width + math::kTileSize - 1) / math::kTileSize) *
                        ((height + math::kTileSize - 1) / math::kTileSize);
  COBGS_CHECK_DTYPE(tile_offsets, at::kLong);
  COBGS_CHECK_DTYPE(flat_ids, at::kInt);
  COBGS_CHECK_SHAPE(tile_offsets, tiles + 1);
  TORCH_CHECK(flat_ids.dim() == 1, "flat_ids must be 1-D, got ", flat_ids.sizes());
  return tiles;
}

// pixel_labels [H, W] int32 on the device of means2d (its values are checked by each
// backend).
inline void check_pixel_labels(const at::Tensor& means2d, const at::Tensor& pixel_labels,
                               int64_t width, int64_t height) {
  COBGS_CHECK_LIKE(pixel_labels, means2d);
  COBGS_CHECK_DTYPE(pixel_labels, at::kInt);
  COBGS_CHECK_SHAPE(pixel_labels, height, width);
}

// check_blend_inputs plus the backward's own inputs; returns (height, width), taken from
// the transmittance.
inline std::pair<int64_t, int64_t> check_blend_bwd_inputs(
    const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
    const at::Tensor& features, const at::Tensor& background, const at::Tensor& tile_offsets,
    const at::Tensor& flat_ids, const at::Tensor& transmittance, const at::Tensor& n_contrib,
    const at::Tensor& v_image, const at::Tensor& v_transmittance) {
  TORCH_CHECK(transmittance.dim() == 2, "transmittance must have shape [H, W], got ",
              transmittance.sizes());
  const int64_t height = transmittance.size(0), width = transmittance.size(1);
  check_blend_inputs(means2d, conics, opacities, features, background, tile_offsets, flat_ids,
                     width, height);
  const int64_t c = features.size(1);
  COBGS_CHECK_LIKE(transmittance, means2d);
  COBGS_CHECK_LIKE(n_contrib, means2d);
  COBGS_CHECK_LIKE(v_image, means2d);
  COBGS_CHECK_LIKE(v_transmittance, means2d);
  COBGS_CHECK_DTYPE(transmittance, means2d.scalar_type());
  COBGS_CHECK_DTYPE(v_image, means2d.scalar_type());
  COBGS_CHECK_DTYPE(v_transmittance, means2d.scalar_type());
  COBGS_CHECK_DTYPE(n_contrib, at::kInt);
  COBGS_CHECK_SHAPE(n_contrib, height, width);
  COBGS_CHECK_SHAPE(v_image, height, width, c);
  COBGS_CHECK_SHAPE(v_transmittance, height, width);
  return {height, width};
}

// Args:
//   means2d [N, 2] pixels          conics [N, 3] (a, b, c) inverse 2D covariance
//   opacities [N]                  features [N, C]         background [C]
//   tile_offsets [tiles + 1] int64, flat_ids [M] int32: the output of bin_tiles
//   width, height: image size in pixels
//   pixel_labels [H, W] int32 (0..num_labels-1, -1 = ignore) or none
//   prep: the prep output of bin_tiles_tight for these means2d / conics / opacities, or
//       none (the pass then computes the same per-Gaussian records itself)
// Returns:
//   image [H, W, C]   transmittance [H, W] (T_final)
//   n_contrib [H, W] int32: 1 + position (in the pixel's tile list) of the last blended
//       Gaussian, 0 if none; the backward pass replays exactly these
//   label_counts [N, K] int32, label_weights [N, K] float32 (Σ α·T) when pixel_labels is
//       given, else both [0, K]
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> blend_cpu(
    const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
    const at::Tensor& features, const at::Tensor& background, const at::Tensor& tile_offsets,
    const at::Tensor& flat_ids, int64_t width, int64_t height,
    const std::optional<at::Tensor>& pixel_labels, int64_t num_labels,
    const std::optional<at::Tensor>& prep, bool check);

// Backward of blend_cpu: v_image [H, W, C] and v_transmittance [H, W] are the incoming
// gradients; transmittance and n_contrib come from the forward pass; prep as in blend_cpu.
// Returns v_means2d [N, 2], v_conics [N, 3], v_opacities [N], v_features [N, C],
// v_background [C].
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> blend_bwd_cpu(
    const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
    const at::Tensor& features, const at::Tensor& background, const at::Tensor& tile_offsets,
    const at::Tensor& flat_ids, const at::Tensor& transmittance, const at::Tensor& n_contrib,
    const at::Tensor& v_image, const at::Tensor& v_transmittance,
    const std::optional<at::Tensor>& prep, bool check);

// The CUDA implementations (csrc/blend/blend_*_cuda.cu; builds with CUDA only).
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> blend_cuda(
    const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
    const at::Tensor& features, const at::Tensor& background, const at::Tensor& tile_offsets,
    const at::Tensor& flat_ids, int64_t width, int64_t height,
    const std::optional<at::Tensor>& pixel_labels, int64_t num_labels,
    const std::optional<at::Tensor>& prep, bool check);
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> blend_bwd_cuda(
    const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
    const at::Tensor& features, const at::Tensor& background, const at::Tensor& tile_offsets,
    const at::Tensor& flat_ids, const at::Tensor& transmittance, const at::Tensor& n_contrib,
    const at::Tensor& v_image, const at::Tensor& v_transmittance,
    const std::optional<at::Tensor>& prep, bool check);

}  // namespace cobgs
