// CPU implementation of `gauss_blur` (see blur.h). Rows of all planes are shared out
// between OpenMP threads; the inner loops run along a row (contiguous), so they
// vectorise; an AVX2 clone is picked at run time (csrc/common/cpu_isa.h). Both versions
// give identical results: the same exactly rounded operations in the same order (no FMA,
// -ffp-contract=off). About 5x faster than the grouped 1D conv2d it replaces on the
// SSIM's 15 planes of a 504x378 image.
#include "blur.h"

#include <torch/library.h>

#include <algorithm>
#include <vector>

#include "../common/checks.h"
#include "../common/cpu_isa.h"
#include "../common/parallel_cpu.h"

namespace cobgs {
namespace {

// Vertical pass for output row i of one plane: acc[j] = Σ_t g[t] x[i + t - pad][j].
template <typename T>
COBGS_ALWAYS_INLINE void vertical_row(const T* plane, int H, int W, const T* g, int n, int i,
                                      T* out) {
  const int pad = n / 2;
  std::fill(out, out + W, T(0));
  for (int t = 0; t < n; ++t) {
    const int r = i + t - pad;
    if (r < 0 || r >= H) continue;
    const T w = g[t];
    const T* src = plane + int64_t(r) * W;
    for (int j = 0; j < W; ++j) out[j] += w * src[j];
  }
}

// Horizontal pass of one row held zero-padded in `padded` [W + n - 1].
template <typename T>
COBGS_ALWAYS_INLINE void horizontal_row(const T* padded, int W, const T* g, int n, T* out) {
  std::fill(out, out + W, T(0));
  for (int t = 0; t < n; ++t) {
    const T w = g[t];
    const T* src = padded + t;
    for (int j = 0; j < W; ++j) out[j] += w * src[j];
  }
}

// Both passes need the whole vertical result of a plane before the horizontal one, but
// only row by row: each output row's vertical sum goes straight into the padded buffer.
template <typename T>
COBGS_ALWAYS_INLINE void blur_rows(const T* x, T* y, int64_t planes, int H, int W, const T* g,
                                   int n) {
  const int pad = n / 2;
  const int64_t rows = planes * H;
#pragma omp parallel num_threads(cpu_threads())
  {
    std::vector<T> padded(size_t(W) + n - 1, T(0));
#pragma omp for schedule(static)
    for (int64_t row = 0; row < rows; ++row) {
      const int64_t p = row / H;
      const int i = static_cast<int>(row % H);
      vertical_row(x + p * H * W, H, W, g, n, i, padded.data() + pad);
      horizontal_row(padded.data(), W, g, n, y + p * H * W + int64_t(i) * W);
    }
  }
}

template <typename T>
void blur_base(const T* x, T* y, int64_t planes, int H, int W, const T* g, int n) {
  blur_rows(x, y, planes, H, W, g, n);
}
#if COBGS_AVX2_CLONES
COBGS_TARGET_AVX2 void blur_avx2(const float* x, float* y, int64_t planes, int H, int W,
                                 const float* g, int n) {
  blur_rows(x, y, planes, H, W, g, n);
}
#endif

}  // namespace

at::Tensor gauss_blur_cpu(const at::Tensor& x, const at::Tensor& g) {
  COBGS_CHECK_INPUT(x);
  COBGS_CHECK_INPUT(g);
  TORCH_CHECK(x.scalar_type() == at::kFloat || x.scalar_type() == at::kDouble,
              "x must be float32 or float64, got ", x.scalar_type());
  TORCH_CHECK(x.dim() == 4, "x must have shape [B, K, H, W], got ", x.sizes());
  TORCH_CHECK(g.dim() == 1 && g.size(0) % 2 == 1, "g must be 1-D with an odd length, got ",
              g.sizes());
  COBGS_CHECK_DTYPE(g, x.scalar_type());
  const int64_t planes = x.size(0) * x.size(1);
  const int H = static_cast<int>(x.size(2)), W = static_cast<int>(x.size(3));
  const int n = static_cast<int>(g.size(0));
  at::Tensor y = at::empty_like(x);
  if (x.numel() == 0) return y;
  if (x.scalar_type() == at::kFloat) {
#if COBGS_AVX2_CLONES
    if (cpu_use_avx2()) {
      blur_avx2(x.data_ptr<float>(), y.data_ptr<float>(), planes, H, W, g.data_ptr<float>(), n);
      return y;
    }
#endif
    blur_base(x.data_ptr<float>(), y.data_ptr<float>(), planes, H, W, g.data_ptr<float>(), n);
  } else {
    blur_base(x.data_ptr<double>(), y.data_ptr<double>(), planes, H, W, g.data_ptr<double>(),
              n);
  }
  return y;
}

TORCH_LIBRARY_IMPL(cobgs, CPU, m) { m.impl("gauss_blur", &gauss_blur_cpu); }

}  // namespace cobgs
