// Op family `project`: EWA projection and culling of 3D Gaussians into one camera.
// Formulas: csrc/common/gs_math.h (project_gaussian, project_gaussian_vjp); contract and
// oracle: cobgs/render/reference.py (project_reference).
#pragma once

#include <torch/types.h>

#include <tuple>

#include "../common/checks.h"

namespace cobgs {

// Shape, dtype and device checks of project / project_bwd (shared by both backends; the
// caller has checked the device type of means).
inline void check_project_inputs(const at::Tensor& means, const at::Tensor& quats,
                                 const at::Tensor& scales, const at::Tensor& viewmat,
                                 const at::Tensor& K, int64_t width, int64_t height) {
  TORCH_CHECK(means.dim() == 2, "means must have shape [N, 3], got ", means.sizes());
  COBGS_CHECK_CONTIGUOUS(means);
  COBGS_CHECK_LIKE(quats, means);
  COBGS_CHECK_LIKE(scales, means);
  TORCH_CHECK(means.scalar_type() == at::kFloat || means.scalar_type() == at::kDouble,
              "means must be float32 or float64, got ", means.scalar_type());
  const int64_t n = means.size(0);
  COBGS_CHECK_SHAPE(means, n, 3);
  COBGS_CHECK_SHAPE(quats, n, 4);
  COBGS_CHECK_SHAPE(scales, n, 3);
  COBGS_CHECK_DTYPE(quats, means.scalar_type());
  COBGS_CHECK_DTYPE(scales, means.scalar_type());
  COBGS_CHECK_LIKE(viewmat, means);
  COBGS_CHECK_LIKE(K, means);
  COBGS_CHECK_SHAPE(viewmat, 4, 4);
  COBGS_CHECK_SHAPE(K, 3, 3);
  COBGS_CHECK_DTYPE(viewmat, means.scalar_type());
  COBGS_CHECK_DTYPE(K, means.scalar_type());
  TORCH_CHECK(width > 0 && height > 0, "width and height must be positive, got ", width,
              " x ", height);
}

// The extra inputs of project_bwd.
inline void check_project_bwd_inputs(const at::Tensor& means, const at::Tensor& radii,
                                     const at::Tensor& v_means2d, const at::Tensor& v_conics,
                                     const at::Tensor& v_depths) {
  const int64_t n = means.size(0);
  COBGS_CHECK_LIKE(radii, means);
  COBGS_CHECK_SHAPE(radii, n);
  COBGS_CHECK_DTYPE(radii, at::kInt);
  for (const auto* t : {&v_means2d, &v_conics, &v_depths}) {
    COBGS_CHECK_LIKE((*t), means);
    COBGS_CHECK_DTYPE((*t), means.scalar_type());
  }
  COBGS_CHECK_SHAPE(v_means2d, n, 2);
  COBGS_CHECK_SHAPE(v_conics, n, 3);
  COBGS_CHECK_SHAPE(v_depths, n);
}

// Args:
//   means    [N, 3] world positions           quats  [N, 4] (w, x, y, z), unnormalised
//   scales   [N, 3] linear std. deviations    viewmat [4, 4] world -> camera (OpenCV)
//   K        [3, 3] pixel intrinsics          width, height: image size in pixels
//   near_plane: Gaussians with camera z <= near_plane are culled
// Returns (all zero for culled Gaussians):
//   means2d [N, 2] pixels, conics [N, 3] (a, b, c) of the inverse 2D covariance,
//   depths [N] camera z, radii [N] int32 (0 = culled)
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> project_cpu(
    const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
    const at::Tensor& viewmat, const at::Tensor& K, int64_t width, int64_t height,
    double near_plane);

// Backward of project_cpu. v_means2d [N, 2], v_conics [N, 3], v_depths [N] are the
// incoming gradients; radii [N] (from the forward) marks the visible Gaussians.
// Returns v_means [N, 3], v_quats [N, 4], v_scales [N, 3] (zero for culled Gaussians).
std::tuple<at::Tensor, at::Tensor, at::Tensor> project_bwd_cpu(
    const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
    const at::Tensor& viewmat, const at::Tensor& K, int64_t width, int64_t height,
    const at::Tensor& radii, const at::Tensor& v_means2d, const at::Tensor& v_conics,
    const at::Tensor& v_depths);

// The CUDA implementations (csrc/project/project_cuda.cu; builds with CUDA only).
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> project_cuda(
    const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
    const at::Tensor& viewmat, const at::Tensor& K, int64_t width, int64_t height,
    double near_plane);
std::tuple<at::Tensor, at::Tensor, at::Tensor> project_bwd_cuda(
    const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
    const at::Tensor& viewmat, const at::Tensor& K, int64_t width, int64_t height,
    const at::Tensor& radii, const at::Tensor& v_means2d, const at::Tensor& v_conics,
    const at::Tensor& v_depths);

}  // namespace cobgs
