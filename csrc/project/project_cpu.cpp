// CPU implementation of the `project` op family (see project.h). The loops live in
// project_lanes_cpu.h, compiled per instruction set and chosen at run time.
#include "project.h"

#include <torch/library.h>

#include <algorithm>
#include <type_traits>

#include "../common/checks.h"
#include "../common/cpu_isa.h"
#include "../common/gs_math.h"
#include "../common/parallel_cpu.h"
#include "../common/prof_cpu.h"
#include "../common/simd_cpu.h"

namespace cobgs {
namespace {

template <typename T>
struct ProjArgs {
  math::Camera<T> cam;
  T near;
  const T* means;   // [N, 3]
  const T* quats;   // [N, 4]
  const T* scales;  // [N, 3]
  T* means2d;       // [N, 2]  (every output element is written)
  T* conics;        // [N, 3]
  T* depths;        // [N]
  int32_t* radii;   // [N]
};

template <typename T>
struct ProjBwdArgs {
  math::Camera<T> cam;
  const T* means;
  const T* quats;
  const T* scales;
  const int32_t* radii;
  const T* v_means2d;
  const T* v_conics;
  const T* v_depths;
  T* v_means;   // [N, 3]  (every output element is written)
  T* v_quats;   // [N, 4]
  T* v_scales;  // [N, 3]
};

}  // namespace

// The loops once per instruction set (float32 in lane vectors; float64 one at a time).
namespace project_base {
#define COBGS_ISA_LEVEL 0
#include "project_lanes_cpu.h"
#undef COBGS_ISA_LEVEL
}  // namespace project_base
#if COBGS_AVX2_CLONES
COBGS_BEGIN_ISA_AVX2
namespace project_avx2 {
#define COBGS_ISA_LEVEL 1
#include "project_lanes_cpu.h"
#undef COBGS_ISA_LEVEL
}  // namespace project_avx2
COBGS_END_ISA
COBGS_BEGIN_ISA_AVX512
namespace project_avx512 {
#define COBGS_ISA_LEVEL 2
#include "project_lanes_cpu.h"
#undef COBGS_ISA_LEVEL
}  // namespace project_avx512
COBGS_END_ISA
#endif

namespace {

// Gaussians in chunks of 256 (whole lane blocks).
constexpr int64_t kChunk = 256;

// float32: the version for this CPU; float64: the baseline one (the float64 path, which
// serves tests and gradcheck, is not bit-identical between the baseline and the AVX-512
// compilation of the projection).
template <typename T, typename F>
F pick(F for_cpu, F base) {
  return std::is_same_v<T, float> ? for_cpu : base;
}

template <typename T>
void project_kernel(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                    const at::Tensor& viewmat, const at::Tensor& K, int64_t width,
                    int64_t height, double near_plane, at::Tensor& means2d, at::Tensor& conics,
                    at::Tensor& depths, at::Tensor& radii) {
  const ProjArgs<T> args{math::make_camera<T>(viewmat.data_ptr<T>(), K.data_ptr<T>(),
                                              static_cast<int>(width), static_cast<int>(height)),
                         static_cast<T>(near_plane),
                         means.data_ptr<T>(),
                         quats.data_ptr<T>(),
                         scales.data_ptr<T>(),
                         means2d.data_ptr<T>(),
                         conics.data_ptr<T>(),
                         depths.data_ptr<T>(),
                         radii.data_ptr<int32_t>()};
  COBGS_PROF_COUNT(kCallsProject, 1);
  COBGS_PROF_SCOPE(kProject);  // (the master thread only)
  const auto fn =
      pick<T>(COBGS_ISA_DISPATCH(project, project_range<T>), &project_base::project_range<T>);
  parallel_ranges(means.size(0), kChunk, [&](int64_t i0, int64_t i1) { fn(args, i0, i1); });
}

template <typename T>
void project_bwd_kernel(const at::Tensor& means, const at::Tensor& quats,
                        const at::Tensor& scales, const at::Tensor& viewmat,
                        const at::Tensor& K, int64_t width, int64_t height,
                        const at::Tensor& radii, const at::Tensor& v_means2d,
                        const at::Tensor& v_conics, const at::Tensor& v_depths,
                        at::Tensor& v_means, at::Tensor& v_quats, at::Tensor& v_scales) {
  const ProjBwdArgs<T> args{math::make_camera<T>(viewmat.data_ptr<T>(), K.data_ptr<T>(),
                                                 static_cast<int>(width),
                                                 static_cast<int>(height)),
                            means.data_ptr<T>(),
                            quats.data_ptr<T>(),
                            scales.data_ptr<T>(),
                            radii.data_ptr<int32_t>(),
                            v_means2d.data_ptr<T>(),
                            v_conics.data_ptr<T>(),
                            v_depths.data_ptr<T>(),
                            v_means.data_ptr<T>(),
                            v_quats.data_ptr<T>(),
                            v_scales.data_ptr<T>()};
  COBGS_PROF_COUNT(kCallsProjectBwd, 1);
  COBGS_PROF_SCOPE(kProjectBwd);  // (the master thread only)
  const auto fn =
      pick<T>(COBGS_ISA_DISPATCH(project, project_bwd_range<T>),
              &project_base::project_bwd_range<T>);
  parallel_ranges(means.size(0), kChunk, [&](int64_t i0, int64_t i1) { fn(args, i0, i1); });
}

}  // namespace

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> project_cpu(
    const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
    const at::Tensor& viewmat, const at::Tensor& K, int64_t width, int64_t height,
    double near_plane) {
  COBGS_CHECK_CPU(means);
  check_project_inputs(means, quats, scales, viewmat, K, width, height);
  const int64_t n = means.size(0);
  // Every element is written by the kernel (zero where culled).
  at::Tensor means2d = at::empty({n, 2}, means.options());
  at::Tensor conics = at::empty({n, 3}, means.options());
  at::Tensor depths = at::empty({n}, means.options());
  at::Tensor radii = at::empty({n}, means.options().dtype(at::kInt));

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
  COBGS_CHECK_CPU(means);
  check_project_inputs(means, quats, scales, viewmat, K, width, height);
  check_project_bwd_inputs(means, radii, v_means2d, v_conics, v_depths);
  // Every element is written by the kernel.
  at::Tensor v_means = at::empty_like(means);
  at::Tensor v_quats = at::empty_like(quats);
  at::Tensor v_scales = at::empty_like(scales);

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
