// CPU implementation of `gauss_blur` and the row passes of `ssim_mean_grad` (see blur.h):
// the row kernels of blur_rows_cpu.h once per instruction set, and the run-time choice
// (csrc/common/cpu_isa.h). All versions give identical results (the same exactly rounded
// operations in the same order). Rows of all planes are shared out between OpenMP
// threads.
#include "blur.h"

#include <torch/library.h>

#include <algorithm>
#include <cstring>
#include <vector>

#include "../common/checks.h"
#include "../common/cpu_isa.h"
#include "../common/gs_math.h"
#include "../common/parallel_cpu.h"
#include "../common/simd_cpu.h"
#include "ssim_math.h"

namespace cobgs {
namespace blur_detail {

namespace blur_base {
#define COBGS_ISA_LEVEL 0
#include "blur_rows_cpu.h"
#undef COBGS_ISA_LEVEL
}  // namespace blur_base
#if COBGS_AVX2_CLONES
COBGS_BEGIN_ISA_AVX2
namespace blur_avx2 {
#define COBGS_ISA_LEVEL 1
#include "blur_rows_cpu.h"
#undef COBGS_ISA_LEVEL
}  // namespace blur_avx2
COBGS_END_ISA
COBGS_BEGIN_ISA_AVX512
namespace blur_avx512 {
#define COBGS_ISA_LEVEL 2
#include "blur_rows_cpu.h"
#undef COBGS_ISA_LEVEL
}  // namespace blur_avx512
COBGS_END_ISA
#endif

template <typename T>
double ssim_mean_grad_planes(const T* x, const T* y, int64_t planes, int H, int W, const T* g,
                             int n, T* parts, T* grad) {
  return COBGS_ISA_DISPATCH(
      blur, ssim_planes<T, false>(x, y, planes, H, W, 1, g, n, parts, grad, {}, nullptr));
}

template <typename T>
double photometric_grad_rows(const T* x, const T* y, int64_t batch, int H, int W, int C,
                             const T* g, int n, T* parts, T* grad, double w_l1, double w_ssim,
                             double* l1_sum) {
  return COBGS_ISA_DISPATCH(
      blur, ssim_planes<T, true>(x, y, batch, H, W * C, C, g, n, parts, grad, {w_l1, w_ssim},
                                 l1_sum));
}

#define COBGS_INSTANTIATE(T)                                                                 \
  template double ssim_mean_grad_planes<T>(const T*, const T*, int64_t, int, int, const T*, \
                                           int, T*, T*);                                    \
  template double photometric_grad_rows<T>(const T*, const T*, int64_t, int, int, int,      \
                                           const T*, int, T*, T*, double, double, double*);
COBGS_INSTANTIATE(float)
COBGS_INSTANTIATE(double)
#undef COBGS_INSTANTIATE

}  // namespace blur_detail

at::Tensor gauss_blur_cpu(const at::Tensor& x, const at::Tensor& g) {
  COBGS_CHECK_CPU(x);
  check_blur_inputs(x, g);
  const int64_t planes = x.size(0) * x.size(1);
  const int H = static_cast<int>(x.size(2)), W = static_cast<int>(x.size(3));
  const int n = static_cast<int>(g.size(0));
  at::Tensor y = at::empty_like(x);
  if (x.numel() == 0) return y;
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "cobgs::gauss_blur", [&] {
    using namespace blur_detail;
    COBGS_ISA_DISPATCH(blur, blur_planes<scalar_t>(x.data_ptr<scalar_t>(),
                                                   y.data_ptr<scalar_t>(), planes, H, W,
                                                   g.data_ptr<scalar_t>(), n));
  });
  return y;
}

TORCH_LIBRARY_IMPL(cobgs, CPU, m) { m.impl("gauss_blur", &gauss_blur_cpu); }

}  // namespace cobgs
