// Op family `project`: EWA projection and culling of 3D Gaussians into one camera.
// Formulas: csrc/common/gs_math.h (project_gaussian, project_gaussian_vjp); contract and
// oracle: cobgs/reference.py (project_reference).
#pragma once

#include <torch/types.h>

#include <tuple>

namespace cobgs {

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

}  // namespace cobgs
