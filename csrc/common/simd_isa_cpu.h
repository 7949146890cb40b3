// The lane helpers that differ per instruction set. Included (no include guard) inside a
// namespace of each kernel version with COBGS_ISA_LEVEL set; see simd_cpu.h. Every
// version computes the same values.
//   0: portable vector-extension code (any CPU; SSE2 on x86-64)
//   1: AVX2 intrinsics, 2: the same under AVX-512 (the compiler then also uses mask and
//      the 16 extra registers); both only for the float32 kernels' 32-bit lanes.
#ifndef COBGS_ISA_LEVEL
#error "define COBGS_ISA_LEVEL before including simd_isa_cpu.h"
#endif

// True when some lane of a mask (or an int vector) is non-zero.
template <typename M>
inline bool any(const M& m) {
  uint64_t w[sizeof(M) / 8];
  std::memcpy(w, &m, sizeof(M));
  uint64_t r = 0;
  for (size_t i = 0; i < sizeof(M) / 8; ++i) r |= w[i];
  return r != 0;
}

// Bit k set when lane k of the mask is set.
template <typename M>
inline uint32_t bits(const M& m) {
  uint32_t b = 0;
  for (int k = 0; k < simd::kLanes; ++k) b |= uint32_t(m[k] != 0) << k;
  return b;
}

// std::min(hi, x) lane-wise, with its NaN behaviour (NaN -> hi).
template <typename V>
inline V min_with(const V& hi, const V& x) {
  return x < hi ? x : hi;
}

#if COBGS_ISA_LEVEL >= 1
inline bool any(const simd::VI& m) {
  const __m256i v = (__m256i)m;
  return !_mm256_testz_si256(v, v);
}
inline uint32_t bits(const simd::VI& m) {
  return static_cast<uint32_t>(_mm256_movemask_ps((__m256)m));
}
// minps(x, hi) is x < hi ? x : hi exactly (the second operand when unordered).
inline simd::Lanes<float>::V min_with(const simd::Lanes<float>::V& hi,
                                      const simd::Lanes<float>::V& x) {
  return (simd::Lanes<float>::V)_mm256_min_ps((__m256)x, (__m256)hi);
}
#endif

// Lane-wise twin of math::gauss_exp(float) (csrc/common/gs_math.h): the same operations
// in the same order, so each lane is bit-identical to the scalar function.
inline simd::Lanes<float>::V gauss_exp(simd::Lanes<float>::V x) {
  typedef simd::Lanes<float>::V V;
  const V lo = simd::splat<V>(-87.0f), hi = simd::splat<V>(88.0f);
  x = min_with(hi, x);  // std::min(88, x)
  x = lo < x ? x : lo;  // std::max(-87, x)
  V n;
  const V y = math::exp_reduced(x, n);  // the scalar function's core, lane-wise
  const simd::VI e = (__builtin_convertvector(n, simd::VI) + 127) << 23;
  V scale;
  std::memcpy(&scale, &e, sizeof(scale));
  return y * scale;
}

// float64 (tests and gradcheck): the library exp per lane, as math::gauss_exp(double).
inline simd::Lanes<double>::V gauss_exp(simd::Lanes<double>::V x) {
  simd::Lanes<double>::V r;
  for (int k = 0; k < simd::kLanes; ++k) r[k] = std::exp(x[k]);
  return r;
}
