// CPU implementation of the `sh_colors` op family (see sh.h). Gaussians in chunks split
// statically between OpenMP threads (results do not depend on the thread count); the
// loops (sh_lanes_cpu.h) run 8 Gaussians at a time in the training case. Replaces a chain
// of about 60 small ATen ops (and their autograd graph) per training iteration.
#include "sh.h"

#include <torch/library.h>

#include <algorithm>
#include <cstring>
#include <type_traits>

#include "../common/checks.h"
#include "../common/cpu_isa.h"
#include "../common/parallel_cpu.h"
#include "../common/prof_cpu.h"
#include "../common/sh_math.h"
#include "../common/simd_cpu.h"
#include "sh_one.h"

namespace cobgs {

// The loops once per instruction set (see sh_lanes_cpu.h).
namespace sh_base {
#define COBGS_ISA_LEVEL 0
#include "sh_lanes_cpu.h"
#undef COBGS_ISA_LEVEL
}  // namespace sh_base
#if COBGS_AVX2_CLONES
COBGS_BEGIN_ISA_AVX2
namespace sh_avx2 {
#define COBGS_ISA_LEVEL 1
#include "sh_lanes_cpu.h"
#undef COBGS_ISA_LEVEL
}  // namespace sh_avx2
COBGS_END_ISA
COBGS_BEGIN_ISA_AVX512
namespace sh_avx512 {
#define COBGS_ISA_LEVEL 2
#include "sh_lanes_cpu.h"
#undef COBGS_ISA_LEVEL
}  // namespace sh_avx512
COBGS_END_ISA
#endif

namespace {

// Gaussians in chunks of 256 (whole lane blocks).
constexpr int64_t kChunk = 256;

}  // namespace

at::Tensor sh_colors_cpu(const at::Tensor& means, const at::Tensor& sh0, const at::Tensor& shN,
                         const at::Tensor& center, int64_t degree) {
  COBGS_CHECK_CPU(means);
  check_sh_inputs(means, sh0, shN, center, degree);
  const int64_t n = means.size(0), M = shN.size(1), C = sh0.size(2);
  at::Tensor out = at::empty({n, C}, means.options());
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "cobgs::sh_colors", [&] {
    const ShArgs<scalar_t> args{means.data_ptr<scalar_t>(), sh0.data_ptr<scalar_t>(),
                                shN.data_ptr<scalar_t>(),   center.data_ptr<scalar_t>(),
                                M, static_cast<int>(C), static_cast<int>(degree),
                                out.data_ptr<scalar_t>()};
    COBGS_PROF_COUNT(kCallsSh, 1);
    COBGS_PROF_SCOPE(kShFwd);  // (the master thread only)
    const auto fn = COBGS_ISA_DISPATCH(sh, sh_forward_range<scalar_t>);
    parallel_ranges(n, kChunk, [&](int64_t i0, int64_t i1) { fn(args, i0, i1); });
  });
  return out;
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> sh_colors_bwd_cpu(
    const at::Tensor& means, const at::Tensor& sh0, const at::Tensor& shN,
    const at::Tensor& center, int64_t degree, const at::Tensor& v_colors) {
  COBGS_CHECK_CPU(means);
  check_sh_inputs(means, sh0, shN, center, degree);
  const int64_t n = means.size(0), M = shN.size(1), C = sh0.size(2);
  check_sh_bwd_input(means, sh0, v_colors);
  // Every element is written by the kernel (no zero fill needed).
  at::Tensor v_means = at::empty_like(means);
  at::Tensor v_sh0 = at::empty_like(sh0);
  at::Tensor v_shN = at::empty_like(shN);
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "cobgs::sh_colors_bwd", [&] {
    const ShBwdArgs<scalar_t> args{means.data_ptr<scalar_t>(),  sh0.data_ptr<scalar_t>(),
                                   shN.data_ptr<scalar_t>(),    center.data_ptr<scalar_t>(),
                                   M,                           static_cast<int>(C),
                                   static_cast<int>(degree),    v_colors.data_ptr<scalar_t>(),
                                   v_means.data_ptr<scalar_t>(), v_sh0.data_ptr<scalar_t>(),
                                   v_shN.data_ptr<scalar_t>()};
    COBGS_PROF_COUNT(kCallsShBwd, 1);
    COBGS_PROF_SCOPE(kShBwd);  // (the master thread only)
    const auto fn = COBGS_ISA_DISPATCH(sh, sh_backward_range<scalar_t>);
    parallel_ranges(n, kChunk, [&](int64_t i0, int64_t i1) { fn(args, i0, i1); });
  });
  return {v_means, v_sh0, v_shN};
}

TORCH_LIBRARY_IMPL(cobgs, CPU, m) {
  m.impl("sh_colors", &sh_colors_cpu);
  m.impl("sh_colors_bwd", &sh_colors_bwd_cpu);
}

}  // namespace cobgs
