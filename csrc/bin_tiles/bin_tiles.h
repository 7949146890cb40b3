// Op family `bin_tiles`: lists, for every 16x16 tile, the Gaussians whose 3-sigma box
// touches it, in front-to-back order. Contract and oracle: cobgs/render/reference.py
// (tile_rects, bin_tiles_reference).
#pragma once

#include <torch/types.h>

#include <tuple>

#include "../common/checks.h"

namespace cobgs {

// Checks shared by both binning ops; returns N.
inline int64_t check_bin_inputs(const at::Tensor& means2d, const at::Tensor& radii,
                                const at::Tensor& depths, int64_t width, int64_t height) {
  COBGS_CHECK_CONTIGUOUS(means2d);
  COBGS_CHECK_LIKE(radii, means2d);
  COBGS_CHECK_LIKE(depths, means2d);
  TORCH_CHECK(means2d.dim() == 2, "means2d must have shape [N, 2], got ", means2d.sizes());
  const int64_t n = means2d.size(0);
  TORCH_CHECK(n < (int64_t(1) << 31), "at most 2^31 - 1 Gaussians are supported, got ", n);
  COBGS_CHECK_SHAPE(means2d, n, 2);
  COBGS_CHECK_SHAPE(radii, n);
  COBGS_CHECK_SHAPE(depths, n);
  COBGS_CHECK_DTYPE(radii, at::kInt);
  COBGS_CHECK_DTYPE(depths, means2d.scalar_type());
  TORCH_CHECK(width > 0 && height > 0, "width and height must be positive, got ", width,
              " x ", height);
  return n;
}

// check_bin_inputs plus the conics and opacities of bin_tiles_tight; returns N.
inline int64_t check_bin_tight_inputs(const at::Tensor& means2d, const at::Tensor& radii,
                                      const at::Tensor& depths, const at::Tensor& conics,
                                      const at::Tensor& opacities, int64_t width,
                                      int64_t height) {
  TORCH_CHECK(means2d.scalar_type() == at::kFloat || means2d.scalar_type() == at::kDouble,
              "means2d must be float32 or float64, got ", means2d.scalar_type());
  const int64_t n = check_bin_inputs(means2d, radii, depths, width, height);
  COBGS_CHECK_LIKE(conics, means2d);
  COBGS_CHECK_LIKE(opacities, means2d);
  COBGS_CHECK_SHAPE(conics, n, 3);
  COBGS_CHECK_SHAPE(opacities, n);
  COBGS_CHECK_DTYPE(conics, means2d.scalar_type());
  COBGS_CHECK_DTYPE(opacities, means2d.scalar_type());
  return n;
}

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

// The CUDA implementations (csrc/bin_tiles/bin_tiles_cuda.cu; builds with CUDA only).
std::tuple<at::Tensor, at::Tensor> bin_tiles_cuda(const at::Tensor& means2d,
                                                  const at::Tensor& radii,
                                                  const at::Tensor& depths, int64_t width,
                                                  int64_t height);
std::tuple<at::Tensor, at::Tensor, at::Tensor> bin_tiles_tight_cuda(
    const at::Tensor& means2d, const at::Tensor& radii, const at::Tensor& depths,
    const at::Tensor& conics, const at::Tensor& opacities, int64_t width, int64_t height);

}  // namespace cobgs
