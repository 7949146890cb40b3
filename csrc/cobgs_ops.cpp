// Schemas of every op in the `cobgs` namespace (one place, as torchvision does). Kernels
// register their implementations per backend with TORCH_LIBRARY_IMPL in their own files;
// autograd formulas and shape-only fake kernels are registered from Python
// (cobgs/render/_ops.py). Tensor shapes are documented in each op family's header.
//
// blend / blend_bwd `check`: whether the CUDA kernels report bad tile lists, labels and
// n_contrib as errors (one synchronisation with the host per call). Bad values are never
// dereferenced either way; rasterize passes False for the lists it made itself. The CPU
// kernels always check (on the host, at no synchronisation cost).
#include <torch/library.h>

#include <cstdint>

namespace {
// The build's error probe (cobgs/render/_build.py): called with bad input after every build,
// in a child process, it must come back to Python as a RuntimeError that still holds its
// numbers. A library carrying its own copy of libstdc++ (a compiler that links it statically)
// crashes or drops the numbers here instead.
int64_t error_probe(int64_t n) {
  TORCH_CHECK(n == 0, "cobgs error probe: ", n, " ", 2.5, " ", -7);
  return n;
}
}  // namespace

TORCH_LIBRARY(cobgs, m) {
  m.def("error_probe(int n) -> int", &error_probe);
  // csrc/project/project.h
  m.def(
      "project(Tensor means, Tensor quats, Tensor scales, Tensor viewmat, Tensor K, "
      "int width, int height, float near_plane) "
      "-> (Tensor means2d, Tensor conics, Tensor depths, Tensor radii)");
  m.def(
      "project_bwd(Tensor means, Tensor quats, Tensor scales, Tensor viewmat, Tensor K, "
      "int width, int height, Tensor radii, Tensor v_means2d, Tensor v_conics, "
      "Tensor v_depths) -> (Tensor v_means, Tensor v_quats, Tensor v_scales)");
  // csrc/bin_tiles/bin_tiles.h
  m.def(
      "bin_tiles(Tensor means2d, Tensor radii, Tensor depths, int width, int height) "
      "-> (Tensor tile_offsets, Tensor flat_ids)");
  m.def(
      "bin_tiles_tight(Tensor means2d, Tensor radii, Tensor depths, Tensor conics, "
      "Tensor opacities, int width, int height) "
      "-> (Tensor tile_offsets, Tensor flat_ids, Tensor prep)");
  // csrc/blend/blend.h
  m.def(
      "blend(Tensor means2d, Tensor conics, Tensor opacities, Tensor features, "
      "Tensor background, Tensor tile_offsets, Tensor flat_ids, int width, int height, "
      "Tensor? pixel_labels, int num_labels, Tensor? prep=None, bool check=True) -> (Tensor image, "
      "Tensor transmittance, Tensor n_contrib, Tensor label_counts, Tensor label_weights)");
  m.def(
      "blend_bwd(Tensor means2d, Tensor conics, Tensor opacities, Tensor features, "
      "Tensor background, Tensor tile_offsets, Tensor flat_ids, Tensor transmittance, "
      "Tensor n_contrib, Tensor v_image, Tensor v_transmittance, Tensor? prep=None, "
      "bool check=True) -> (Tensor v_means2d, "
      "Tensor v_conics, Tensor v_opacities, Tensor v_features, Tensor v_background)");
  // csrc/sh/sh.h
  m.def(
      "sh_colors(Tensor means, Tensor sh0, Tensor shN, Tensor center, int degree) "
      "-> Tensor colors");
  m.def(
      "sh_colors_bwd(Tensor means, Tensor sh0, Tensor shN, Tensor center, int degree, "
      "Tensor v_colors) -> (Tensor v_means, Tensor v_sh0, Tensor v_shN)");
  // csrc/blur/blur.h
  m.def("gauss_blur(Tensor x, Tensor g) -> Tensor");
  m.def("ssim_mean_grad(Tensor x, Tensor y, Tensor g) -> (Tensor mean, Tensor grad)");
  m.def("photometric_loss_grad(Tensor img, Tensor ref, Tensor g, float ssim_weight) -> "
        "(Tensor l1, Tensor ssim, Tensor grad)");
}
