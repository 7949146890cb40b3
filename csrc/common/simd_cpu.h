// Fixed-width lane vectors for the CPU blending kernels (GCC/Clang vector extensions).
//
// A block is 8 consecutive pixels of one tile row; the kernels process a row segment as
// one or two whole blocks with these types. The vector extensions are portable: the same
// source compiles to SSE2 in the baseline build (two 4-wide halves per float block) and to
// AVX2 in the AVX2 clone, and both compute exactly the same lane-wise IEEE operations
// (no FMA contraction: -ffp-contract=off), so the two builds are bit-identical. Lane-wise
// ternaries `m ? a : b` need an integer mask vector with the same lane size as a and b.
//
// Loads and stores go through memcpy (unaligned-safe, no aliasing questions); compilers
// turn them into single vector moves.
//
// Instruction-set versions. A kernel written once in a multiply-included header is
// compiled in several namespaces, each between COBGS_BEGIN_ISA_* and COBGS_END_ISA (every
// function defined in between gets that target), with COBGS_ISA_LEVEL 0 (baseline),
// 1 (AVX2) or 2 (AVX-512 on 256-bit vectors: 32 registers and mask registers). The
// helpers that differ per instruction set (any, bits, min_with, gauss_exp) come from
// simd_isa_cpu.h, included the same way. All these versions compute bit-identical results;
// the fast versions (COBGS_BEGIN_ISA_*_FAST, the blending kernels only) fuse multiply-adds
// and are compared with tolerances instead (tests/render/test_cpu_fast_path.py).
#pragma once

#include <cmath>
#include <cstdint>
#include <cstring>

#include "cpu_isa.h"

#if COBGS_AVX2_CLONES
#include <immintrin.h>
#endif

#if COBGS_AVX2_CLONES && defined(__clang__)
#define COBGS_BEGIN_ISA_AVX2 \
  _Pragma("clang attribute push(__attribute__((target(\"avx2\"))), apply_to = function)")
#define COBGS_BEGIN_ISA_AVX512                                                              \
  _Pragma(                                                                                  \
      "clang attribute push(__attribute__((target(\"avx2,avx512f,avx512vl,avx512dq,avx512bw\"))), apply_to = function)")
#define COBGS_END_ISA _Pragma("clang attribute pop")
// Clang: the fast versions get FMA instructions but no contraction (-ffp-contract=off
// stays), so there they compute what the exact versions compute.
#define COBGS_BEGIN_ISA_AVX2_FAST \
  _Pragma("clang attribute push(__attribute__((target(\"avx2,fma\"))), apply_to = function)")
#define COBGS_BEGIN_ISA_AVX512_FAST                                                             \
  _Pragma(                                                                                      \
      "clang attribute push(__attribute__((target(\"avx2,fma,avx512f,avx512vl,avx512dq,avx512bw\"))), apply_to = function)")
#elif COBGS_AVX2_CLONES
#define COBGS_BEGIN_ISA_AVX2 _Pragma("GCC push_options") _Pragma("GCC target(\"avx2\")")
#define COBGS_BEGIN_ISA_AVX512 \
  _Pragma("GCC push_options") _Pragma("GCC target(\"avx2,avx512f,avx512vl,avx512dq,avx512bw\")")
// The fast versions (the CPU fast path, cpu_isa.h): the same source with fused
// multiply-adds: FMA in the target and a*b+c contracted (GCC's optimize pragma overrides
// -ffp-contract=off for the functions in between).
#define COBGS_BEGIN_ISA_AVX2_FAST                                     \
  _Pragma("GCC push_options") _Pragma("GCC target(\"avx2,fma\")") \
      _Pragma("GCC optimize(\"fp-contract=fast\")")
#define COBGS_BEGIN_ISA_AVX512_FAST                                                       \
  _Pragma("GCC push_options")                                                             \
      _Pragma("GCC target(\"avx2,fma,avx512f,avx512vl,avx512dq,avx512bw\")")            \
          _Pragma("GCC optimize(\"fp-contract=fast\")")
#define COBGS_END_ISA _Pragma("GCC pop_options")
#endif

namespace cobgs {
namespace simd {

constexpr int kLanes = 8;

typedef int32_t VI __attribute__((vector_size(32)));  // 8 x int32 (ranks, labels, masks)

template <typename T>
struct Lanes;

template <>
struct Lanes<float> {
  typedef float V __attribute__((vector_size(32)));
  typedef int32_t M __attribute__((vector_size(32)));  // lane masks: -1 / 0
};

template <>
struct Lanes<double> {
  typedef double V __attribute__((vector_size(64)));
  typedef int64_t M __attribute__((vector_size(64)));
};

template <typename Vec>
inline Vec load(const void* p) {
  Vec v;
  std::memcpy(&v, p, sizeof(Vec));
  return v;
}

template <typename Vec>
inline void store(void* p, const Vec& v) {
  std::memcpy(p, &v, sizeof(Vec));
}

template <typename Vec, typename S>
inline Vec splat(S s) {
  return Vec{} + s;  // 0 + s is exact
}

// int32 lanes <-> the mask type of T's lanes (sign extension / truncation keep -1 and 0).
inline Lanes<float>::M to_mask(VI m, float) { return m; }
inline Lanes<double>::M to_mask(VI m, double) { return __builtin_convertvector(m, Lanes<double>::M); }
inline VI to_i32(Lanes<float>::M m) { return m; }
inline VI to_i32(Lanes<double>::M m) { return __builtin_convertvector(m, VI); }

// Sum of the 8 lanes in a fixed pairwise order (the same in every build).
template <typename V>
inline auto hsum(const V& v) -> decltype(v[0] + v[0]) {
  return ((v[0] + v[1]) + (v[2] + v[3])) + ((v[4] + v[5]) + (v[6] + v[7]));
}


// In-place transpose of 8 lane vectors of 8 floats: afterwards r[j][i] is the former
// r[i][j]. Three rounds of two-input shuffles (the usual unpack / shuffle / 128-bit
// permute network on AVX); only moves values.
COBGS_ALWAYS_INLINE void transpose8(Lanes<float>::V r[8]) {
  typedef Lanes<float>::V V;
  V t[8], s[8];
  for (int i = 0; i < 8; i += 2) {
    t[i] = __builtin_shufflevector(r[i], r[i + 1], 0, 8, 1, 9, 4, 12, 5, 13);
    t[i + 1] = __builtin_shufflevector(r[i], r[i + 1], 2, 10, 3, 11, 6, 14, 7, 15);
  }
  for (int i = 0; i < 8; i += 4)
    for (int h = 0; h < 2; ++h) {
      s[i + h] = __builtin_shufflevector(t[i + h], t[i + h + 2], 0, 1, 8, 9, 4, 5, 12, 13);
      s[i + h + 2] = __builtin_shufflevector(t[i + h], t[i + h + 2], 2, 3, 10, 11, 6, 7, 14, 15);
    }
  // s[0]: columns 0 / 4 of rows 0-3 in its halves; s[2]: 1 / 5; s[1]: 2 / 6; s[3]: 3 / 7.
  const int col_of[4] = {0, 2, 1, 3};
  for (int q = 0; q < 4; ++q) {
    const int c = col_of[q];
    r[c] = __builtin_shufflevector(s[q], s[q + 4], 0, 1, 2, 3, 8, 9, 10, 11);
    r[c + 4] = __builtin_shufflevector(s[q], s[q + 4], 4, 5, 6, 7, 12, 13, 14, 15);
  }
}

// out[i] = hsum(v[i]) for 8 vectors at once, each with hsum's pairwise order (so the
// same bits). Float lanes: one 8x8 transpose puts lane k of every vector in t[k], and the
// pairwise tree over t[0..7] adds lane i of v[i] in hsum's order (about a third of the
// instructions of 8 separate sums); other lane types sum one vector at a time.
template <typename V, typename S>
COBGS_ALWAYS_INLINE void hsum8(const V v[8], S out[8]) {
  if constexpr (sizeof(S) == 4 && sizeof(V) == 8 * sizeof(S)) {
    V t[8];
    for (int i = 0; i < 8; ++i) t[i] = v[i];
    transpose8(t);
    store(out, ((t[0] + t[1]) + (t[2] + t[3])) + ((t[4] + t[5]) + (t[6] + t[7])));
  } else {
    for (int i = 0; i < 8; ++i) out[i] = hsum(v[i]);
  }
}

}  // namespace simd
}  // namespace cobgs
