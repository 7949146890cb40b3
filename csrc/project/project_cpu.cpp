// CPU implementation of the `project` op family (see project.h).
#include "project.h"

#include <torch/library.h>

#include "../common/checks.h"
#include "../common/gs_math.h"
#include "../common/parallel_cpu.h"
#include "../common/prof_cpu.h"

namespace cobgs {
namespace {

void check_camera(const at::Tensor& means, const at::Tensor& viewmat, const at::Tensor& K,
                  int64_t width, int64_t height) {
  COBGS_CHECK_INPUT(viewmat);
  COBGS_CHECK_INPUT(K);
  COBGS_CHECK_SHAPE(viewmat, 4, 4);
  COBGS_CHECK_SHAPE(K, 3, 3);
  COBGS_CHECK_DTYPE(viewmat, means.scalar_type());
  COBGS_CHECK_DTYPE(K, means.scalar_type());
  TORCH_CHECK(width > 0 && height > 0, "width and height must be positive, got ", width,
              " x ", height);
}

void check_gaussians(const at::Tensor& means, const at::Tensor& quats,
                     const at::Tensor& scales) {
  COBGS_CHECK_INPUT(means);
  COBGS_CHECK_INPUT(quats);
  COBGS_CHECK_INPUT(scales);
  TORCH_CHECK(means.scalar_type() == at::kFloat || means.scalar_type() == at::kDouble,
              "means must be float32 or float64, got ", means.scalar_type());
  const int64_t n = means.size(0);
  COBGS_CHECK_SHAPE(means, n, 3);
  COBGS_CHECK_SHAPE(quats, n, 4);
  COBGS_CHECK_SHAPE(scales, n, 3);
  COBGS_CHECK_DTYPE(quats, means.scalar_type());
  COBGS_CHECK_DTYPE(scales, means.scalar_type());
}


template <typename T>
void project_kernel(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                    const at::Tensor& viewmat, const at::Tensor& K, int64_t width,
                    int64_t height, double near_plane, at::Tensor& means2d, at::Tensor& conics,
                    at::Tensor& depths, at::Tensor& radii) {
  const int64_t n = means.size(0);
  const auto cam = math::make_camera<T>(viewmat.data_ptr<T>(), K.data_ptr<T>(),
                                        static_cast<int>(width), static_cast<int>(height));
  const T* m = means.data_ptr<T>();
  const T* q = quats.data_ptr<T>();
  const T* s = scales.data_ptr<T>();
  T* m2 = means2d.data_ptr<T>();
  T* co = conics.data_ptr<T>();
  T* d = depths.data_ptr<T>();
  int32_t* r = radii.data_ptr<int32_t>();
  const T near = static_cast<T>(near_plane);
  COBGS_PROF_COUNT(kCallsProject, 1);
#pragma omp parallel num_threads(cpu_threads())
  {
    COBGS_PROF_SCOPE(kProject);
#pragma omp for schedule(static)
    for (int64_t i = 0; i < n; ++i) {
      const auto p = math::project_gaussian<T>(cam, m + 3 * i, q + 4 * i, s + 3 * i, near);
      if (!p.visible) continue;
      m2[2 * i] = p.mx;
      m2[2 * i + 1] = p.my;
      co[3 * i] = p.ca;
      co[3 * i + 1] = p.cb;
      co[3 * i + 2] = p.cc;
      d[i] = p.depth;
      r[i] = p.radius;
    }
  }
}

template <typename T>
void project_bwd_kernel(const at::Tensor& means, const at::Tensor& quats,
                        const at::Tensor& scales, const at::Tensor& viewmat,
                        const at::Tensor& K, int64_t width, int64_t height,
                        const at::Tensor& radii, const at::Tensor& v_means2d,
                        const at::Tensor& v_conics, const at::Tensor& v_depths,
                        at::Tensor& v_means, at::Tensor& v_quats, at::Tensor& v_scales) {
  const int64_t n = means.size(0);
  const auto cam = math::make_camera<T>(viewmat.data_ptr<T>(), K.data_ptr<T>(),
                                        static_cast<int>(width), static_cast<int>(height));
  const T* m = means.data_ptr<T>();
  const T* q = quats.data_ptr<T>();
  const T* s = scales.data_ptr<T>();
  const int32_t* r = radii.data_ptr<int32_t>();
  const T* vm2 = v_means2d.data_ptr<T>();
  const T* vco = v_conics.data_ptr<T>();
  const T* vd = v_depths.data_ptr<T>();
  T* om = v_means.data_ptr<T>();
  T* oq = v_quats.data_ptr<T>();
  T* os = v_scales.data_ptr<T>();
  COBGS_PROF_COUNT(kCallsProjectBwd, 1);
#pragma omp parallel num_threads(cpu_threads())
  {
    COBGS_PROF_SCOPE(kProjectBwd);
#pragma omp for schedule(static)
    for (int64_t i = 0; i < n; ++i) {
      if (r[i] <= 0) continue;
      // A Gaussian that received no gradient (e.g. behind opaque pixels everywhere in
      // this view) contributes zero: skip the recomputation (outputs start at zero).
      if (vm2[2 * i] == T(0) && vm2[2 * i + 1] == T(0) && vco[3 * i] == T(0) &&
          vco[3 * i + 1] == T(0) && vco[3 * i + 2] == T(0) && vd[i] == T(0))
        continue;
      math::project_gaussian_vjp<T>(cam, m + 3 * i, q + 4 * i, s + 3 * i, vm2[2 * i],
                                    vm2[2 * i + 1], vco[3 * i], vco[3 * i + 1],
                                    vco[3 * i + 2], vd[i], om + 3 * i, oq + 4 * i, os + 3 * i);
    }
  }
}

}  // namespace

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> project_cpu(
    const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
    const at::Tensor& viewmat, const at::Tensor& K, int64_t width, int64_t height,
    double near_plane) {
  TORCH_CHECK(means.dim() == 2, "means must have shape [N, 3], got ", means.sizes());
  check_gaussians(means, quats, scales);
  check_camera(means, viewmat, K, width, height);
  const int64_t n = means.size(0);
  at::Tensor means2d = at::zeros({n, 2}, means.options());
  at::Tensor conics = at::zeros({n, 3}, means.options());
  at::Tensor depths = at::zeros({n}, means.options());
  at::Tensor radii = at::zeros({n}, means.options().dtype(at::kInt));

  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "cobgs::project", [&] {
    project_kernel<scalar_t>(means, quats, scales, viewmat, K, width, height, near_plane,
                             means2d, conics, depths, radii);
  });
  return {means2d, conics, depths, radii};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> project_bwd_cpu(
    const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
    const at::Tensor& viewmat, const at::Tensor& K, int64_t width, int64_t height,
    const at::Tensor& radii, const at::Tensor& v_means2d, const at::Tensor& v_conics,
    const at::Tensor& v_depths) {
  TORCH_CHECK(means.dim() == 2, "means must have shape [N, 3], got ", means.sizes());
  check_gaussians(means, quats, scales);
  check_camera(means, viewmat, K, width, height);
  const int64_t n = means.size(0);
  COBGS_CHECK_INPUT(radii);
  COBGS_CHECK_SHAPE(radii, n);
  COBGS_CHECK_DTYPE(radii, at::kInt);
  for (const auto* t : {&v_means2d, &v_conics, &v_depths}) {
    COBGS_CHECK_INPUT((*t));
    COBGS_CHECK_DTYPE((*t), means.scalar_type());
  }
  COBGS_CHECK_SHAPE(v_means2d, n, 2);
  COBGS_CHECK_SHAPE(v_conics, n, 3);
  COBGS_CHECK_SHAPE(v_depths, n);
  at::Tensor v_means = at::zeros_like(means);
  at::Tensor v_quats = at::zeros_like(quats);
  at::Tensor v_scales = at::zeros_like(scales);

  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "cobgs::project_bwd", [&] {
    project_bwd_kernel<scalar_t>(means, quats, scales, viewmat, K, width, height, radii,
                                 v_means2d, v_conics, v_depths, v_means, v_quats, v_scales);
  });
  return {v_means, v_quats, v_scales};
}

TORCH_LIBRARY_IMPL(cobgs, CPU, m) {
  m.impl("project", &project_cpu);
  m.impl("project_bwd", &project_bwd_cpu);
}

}  // namespace cobgs
