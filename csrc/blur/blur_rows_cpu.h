// Row kernels of gauss_blur and ssim_mean_grad, written once and compiled once per
// instruction set: included (no include guard) inside a namespace of blur_cpu.cpp between
// COBGS_BEGIN_ISA_* / COBGS_END_ISA (csrc/common/simd_cpu.h).
//
// The blur is a vertical then a horizontal pass of the same odd-length kernel g with zero
// padding. A thread produces one output row at a time: the vertical sums of the row go
// into a zero-padded row buffer, the horizontal pass reads that buffer. Both passes keep
// their sums in registers for 8 columns at a time (lane vectors; the last W % 8 columns
// one at a time with the same lane-generic code), adding the taps in the order t = 0 .. n-1
// and skipping rows outside the image. Every output is therefore the same rounded sum as
// the plain two-loop formulation, in every instruction set (no FMA: -ffp-contract=off).
//
// ssim_mean_grad fuses the statistics into the passes: pass 1 blurs x, y, x², y², xy of a
// row straight from x and y (the products are formed per tap, never stored as planes),
// evaluates the SSIM terms on the blurred row and writes the three per-pixel partial
// derivatives; pass 2 blurs those and combines them with x and y into the gradient.
//
// Rows are `R` values long and the horizontal taps are `step` values apart: planar images
// (one channel per plane) have R = W and step 1; channel-interleaved rows ([H, W, C],
// the renderer's layout) have R = W·C and step C, which blurs each channel on its own
// without reordering the image. Each output is the same sum either way.

template <typename V, typename T>
COBGS_ALWAYS_INLINE V ld(const T* p) {
  if constexpr (math::LaneTraits<V>::kVector) {
    V v;
    std::memcpy(&v, p, sizeof(V));
    return v;
  } else {
    return *p;
  }
}

template <typename V, typename T>
COBGS_ALWAYS_INLINE void st(T* p, const V& v) {
  if constexpr (math::LaneTraits<V>::kVector) {
    std::memcpy(p, &v, sizeof(V));
  } else {
    *p = v;
  }
}

// Columns [j, j + lanes) of the vertical pass of K planes for output row i:
// out[k][j..] = Σ_t g[t] plane_k[i + t - n/2][j..] over the rows inside the image.
template <typename V, int K, typename T>
COBGS_ALWAYS_INLINE void vertical_block(const T* const* planes, int H, int W, const T* g,
                                        int n, int i, int j, T* const* out) {
  const int pad = n / 2;
  V acc[K];
  for (int k = 0; k < K; ++k) acc[k] = math::splat_lanes<V>(T(0));
  const int t0 = std::max(0, pad - i), t1 = std::min(n, H + pad - i);
  for (int t = t0; t < t1; ++t) {
    const V w = math::splat_lanes<V>(g[t]);
    const int64_t off = int64_t(i + t - pad) * W + j;
    for (int k = 0; k < K; ++k) acc[k] += w * ld<V>(planes[k] + off);
  }
  for (int k = 0; k < K; ++k) st(out[k] + j, acc[k]);
}

// The same for the five SSIM statistics x, y, x², y², xy of one plane of x and y.
template <typename V, typename T>
COBGS_ALWAYS_INLINE void vertical_stats_block(const T* x, const T* y, int H, int W, const T* g,
                                              int n, int i, int j, T* const* out) {
  const int pad = n / 2;
  V acc[5];
  for (int k = 0; k < 5; ++k) acc[k] = math::splat_lanes<V>(T(0));
  const int t0 = std::max(0, pad - i), t1 = std::min(n, H + pad - i);
  for (int t = t0; t < t1; ++t) {
    const V w = math::splat_lanes<V>(g[t]);
    const int64_t off = int64_t(i + t - pad) * W + j;
    const V xv = ld<V>(x + off), yv = ld<V>(y + off);
    acc[0] += w * xv;
    acc[1] += w * yv;
    acc[2] += w * (xv * xv);
    acc[3] += w * (yv * yv);
    acc[4] += w * (xv * yv);
  }
  for (int k = 0; k < 5; ++k) st(out[k] + j, acc[k]);
}

// Columns [j, j + lanes) of the horizontal pass of K zero-padded rows (padded[k][c] holds
// column c - (n/2)·step): h[k] = Σ_t g[t] padded[k][j + t·step].
template <typename V, int K, typename T>
COBGS_ALWAYS_INLINE void horizontal_block(const T* const* padded, const T* g, int n, int step,
                                          int j, V* h) {
  for (int k = 0; k < K; ++k) h[k] = math::splat_lanes<V>(T(0));
  for (int t = 0; t < n; ++t) {
    const V w = math::splat_lanes<V>(g[t]);
    for (int k = 0; k < K; ++k) h[k] += w * ld<V>(padded[k] + j + t * step);
  }
}

// fn(j, V{}) over the columns of a row: blocks of 8 lanes, then the rest one at a time.
template <typename T, typename F>
COBGS_ALWAYS_INLINE void for_column_blocks(int W, const F& fn) {
  using V = typename simd::Lanes<T>::V;
  int j = 0;
  for (; j + simd::kLanes <= W; j += simd::kLanes) fn(j, V{});
  for (; j < W; ++j) fn(j, T{});
}

// Per-thread zero-padded row buffers for K rows of R values, (n/2)·step zeros each side.
template <typename T, int K>
struct PaddedRows {
  std::vector<T> buf;
  T* row[K];
  PaddedRows(int R, int n, int step) : buf(size_t(K) * (R + (n - 1) * step), T(0)) {
    for (int k = 0; k < K; ++k) row[k] = buf.data() + size_t(k) * (R + (n - 1) * step);
  }
};

// y = blur(x) for `planes` planes of H x W.
template <typename T>
void blur_planes(const T* x, T* y, int64_t planes, int H, int W, const T* g, int n) {
  const int pad = n / 2;
  const int64_t P = int64_t(H) * W;
#pragma omp parallel num_threads(cpu_threads())
  {
    PaddedRows<T, 1> rows(W, n, 1);
    T* const vert[1] = {rows.row[0] + pad};
#pragma omp for schedule(static)
    for (int64_t r = 0; r < planes * H; ++r) {
      const int64_t p = r / H;
      const int i = static_cast<int>(r % H);
      const T* const src[1] = {x + p * P};
      T* out = y + p * P + int64_t(i) * W;
      for_column_blocks<T>(W, [&](int j, auto lane) {
        using V = decltype(lane);
        vertical_block<V, 1>(src, H, W, g, n, i, j, vert);
      });
      for_column_blocks<T>(W, [&](int j, auto lane) {
        using V = decltype(lane);
        V h[1];
        horizontal_block<V, 1>(rows.row, g, n, 1, j, h);
        st(out + j, h[0]);
      });
    }
  }
}

// The per-pixel weights of pass 2's output. Plain SSIM gradient: grad = d mean(S) / dx.
// Photometric loss (kL1 true): grad = d/dx [l1_weight·Σ|x − y| + ssim_weight·mean(S)]
// (the caller folds the loss's constants and signs into the two weights).
struct LossWeights {
  double l1 = 0.0, ssim = 1.0;
};

// ssim_mean_grad on `planes` planes of H rows of R values (taps `step` apart, see the top
// of this file): writes the gradient into grad and returns Σ S over all values, and with
// kL1 Σ |x − y| in *l1_sum. `parts` is scratch for 3 x planes x H x R values. Sums add
// the values of a row in order, then the rows in order: they do not depend on the
// thread count.
template <typename T, bool kL1>
double ssim_planes(const T* x, const T* y, int64_t planes, int H, int R, int step, const T* g,
                   int n, T* parts, T* grad, LossWeights wts, double* l1_sum) {
  const int pad = (n / 2) * step;
  const int64_t P = int64_t(H) * R, rows_total = planes * H, part_stride = planes * P;
  const T c1 = static_cast<T>(kSsimC1), c2 = static_cast<T>(kSsimC2);
  const T inv_n = T(1) / static_cast<T>(planes * P);
  const T w_l1 = static_cast<T>(wts.l1), w_ssim = static_cast<T>(wts.ssim);
  std::vector<double> row_sum(static_cast<size_t>(rows_total));
  std::vector<double> row_l1(kL1 ? static_cast<size_t>(rows_total) : 0);
#pragma omp parallel num_threads(cpu_threads())
  {
    PaddedRows<T, 5> rows(R, n, step);
    T* vert[5];
    for (int k = 0; k < 5; ++k) vert[k] = rows.row[k] + pad;
    // Pass 1: the five blurred statistics of a row, the SSIM terms and the partials
    // ∂S/∂μx, ∂S/∂E[x²], ∂S/∂E[xy] (formulas in ssim_cpu.cpp).
#pragma omp for schedule(static)
    for (int64_t r = 0; r < rows_total; ++r) {
      const int64_t p = r / H;
      const int i = static_cast<int>(r % H);
      for_column_blocks<T>(R, [&](int j, auto lane) {
        using V = decltype(lane);
        vertical_stats_block<V>(x + p * P, y + p * P, H, R, g, n, i, j, vert);
      });
      T* d0 = parts + p * P + int64_t(i) * R;
      double sum = 0.0;
      for_column_blocks<T>(R, [&](int j, auto lane) {
        using V = decltype(lane);
        V s[5];
        horizontal_block<V, 5>(rows.row, g, n, step, j, s);
        const ssim::Terms<V> t = ssim::terms<V, T>(s[0], s[1], s[2], s[3], s[4], c1, c2);
        if constexpr (math::LaneTraits<V>::kVector) {
          for (int k = 0; k < simd::kLanes; ++k) sum += static_cast<double>(t.s[k]);
        } else {
          sum += static_cast<double>(t.s);
        }
        st(d0 + j, t.d_mu);
        st(d0 + part_stride + j, t.d_xx);
        st(d0 + 2 * part_stride + j, t.d_xy);
      });
      row_sum[static_cast<size_t>(r)] = sum;
    }
    // (implicit barrier: pass 2 reads the partials of neighbouring rows)
    // Pass 2: blur the partials, d mean / dx = (b0 + 2 x b1 + y b2) / numel.
#pragma omp for schedule(static)
    for (int64_t r = 0; r < rows_total; ++r) {
      const int64_t p = r / H;
      const int i = static_cast<int>(r % H);
      const T* const src[3] = {parts + p * P, parts + part_stride + p * P,
                               parts + 2 * part_stride + p * P};
      for_column_blocks<T>(R, [&](int j, auto lane) {
        using V = decltype(lane);
        vertical_block<V, 3>(src, H, R, g, n, i, j, vert);
      });
      const int64_t o = p * P + int64_t(i) * R;
      double l1 = 0.0;
      for_column_blocks<T>(R, [&](int j, auto lane) {
        using V = decltype(lane);
        V q[3];
        horizontal_block<V, 3>(rows.row, g, n, step, j, q);
        const V xv = ld<V>(x + o + j), yv = ld<V>(y + o + j);
        const V ssim_grad = ssim::grad<V, T>(q, xv, yv, inv_n);
        if constexpr (kL1) {
          const V diff = xv - yv;
          st(grad + o + j, w_l1 * ssim::sign<V, T>(diff) + w_ssim * ssim_grad);
          const V ad = ssim::abs<V, T>(diff);
          if constexpr (math::LaneTraits<V>::kVector) {
            for (int k = 0; k < simd::kLanes; ++k) l1 += static_cast<double>(ad[k]);
          } else {
            l1 += static_cast<double>(ad);
          }
        } else {
          st(grad + o + j, ssim_grad);
        }
      });
      if constexpr (kL1) row_l1[static_cast<size_t>(r)] = l1;
    }
  }
  double total = 0.0;
  for (const double s : row_sum) total += s;
  if constexpr (kL1) {
    double l1 = 0.0;
    for (const double s : row_l1) l1 += s;
    *l1_sum = l1;
  }
  return total;
}
