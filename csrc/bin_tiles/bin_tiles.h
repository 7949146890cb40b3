// Op family `bin_tiles`: lists, for every 16x16 tile, the Gaussians whose 3-sigma box
// touches it, in front-to-back order. Contract and oracle: cobgs/reference.py
// (tile_rects, bin_tiles_reference).
#pragma once

#include <torch/types.h>

#include <tuple>

namespace cobgs {

// Args:
//   means2d [N, 2] pixels, radii [N] int32 (0 = culled), depths [N] camera z
//   width, height: image size in pixels
// Returns:
//   tile_offsets [tiles_y * tiles_x + 1] int64: tile t (row-major) owns
//       flat_ids[tile_offsets[t] : tile_offsets[t + 1]]
//   flat_ids [M] int32 Gaussian indices; each tile's run sorted by depth, ties by index.
// A Gaussian covers tiles [floor((mx - r) / 16), ceil((mx + r) / 16)) in x (same in y),
// clamped to the grid.
std::tuple<at::Tensor, at::Tensor> bin_tiles_cpu(const at::Tensor& means2d,
                                                 const at::Tensor& radii,
                                                 const at::Tensor& depths, int64_t width,
                                                 int64_t height);

// bin_tiles with tight lists: a Gaussian is listed only in the tiles of its 3-sigma box
// that also meet the pixel box where it can reach alpha >= 1/255 (the box blend computes
// from conics and opacities; about half of the 3-sigma lists on trained scenes). Every
// pixel gets exactly the blended Gaussians it gets from the bin_tiles lists, in the same
// order, so images, transmittance and gradients are the same; n_contrib (a position in
// the list) differs. Also returns prep [N, record size] uint8: blend's per-Gaussian
// records, which blend and blend_bwd take instead of computing them again.
std::tuple<at::Tensor, at::Tensor, at::Tensor> bin_tiles_tight_cpu(
    const at::Tensor& means2d, const at::Tensor& radii, const at::Tensor& depths,
    const at::Tensor& conics, const at::Tensor& opacities, int64_t width, int64_t height);

}  // namespace cobgs
