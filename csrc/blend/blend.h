// Op family `blend`: front-to-back alpha blending of depth-sorted Gaussians per 16x16
// tile, with optional per-label contribution statistics, and its backward pass.
// Per-pixel rule: csrc/common/gs_math.h; contract and oracle: cobgs/reference.py
// (blend_reference).
#pragma once

#include <torch/types.h>

#include <optional>
#include <tuple>

namespace cobgs {

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
    const std::optional<at::Tensor>& prep);

// Backward of blend_cpu: v_image [H, W, C] and v_transmittance [H, W] are the incoming
// gradients; transmittance and n_contrib come from the forward pass; prep as in blend_cpu.
// Returns v_means2d [N, 2], v_conics [N, 3], v_opacities [N], v_features [N, C],
// v_background [C].
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> blend_bwd_cpu(
    const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
    const at::Tensor& features, const at::Tensor& background, const at::Tensor& tile_offsets,
    const at::Tensor& flat_ids, const at::Tensor& transmittance, const at::Tensor& n_contrib,
    const at::Tensor& v_image, const at::Tensor& v_transmittance,
    const std::optional<at::Tensor>& prep);

}  // namespace cobgs
