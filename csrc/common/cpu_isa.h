// Run-time choice of the SIMD width for the hot CPU loops.
//
// The extension is compiled for the baseline of the architecture (no -march=native, so a
// cached build runs on every CPU of that architecture). On x86-64 the per-tile kernels
// are compiled a second time for AVX2 (function attribute target("avx2")) and chosen at
// run time when the CPU has it. Both versions compute bit-identical results: the loops
// only use exactly rounded operations, and -ffp-contract=off forbids fused multiply-adds.
// COBGS_DISABLE_AVX2=1 forces the baseline version (tests compare the two).
#pragma once

#include <cstdlib>
#include <cstring>

#if (defined(__GNUC__) || defined(__clang__)) && (defined(__x86_64__) || defined(__i386__))
#define COBGS_AVX2_CLONES 1
#define COBGS_TARGET_AVX2 __attribute__((target("avx2")))
#else
#define COBGS_AVX2_CLONES 0
#define COBGS_TARGET_AVX2
#endif

#if defined(__GNUC__) || defined(__clang__)
#define COBGS_ALWAYS_INLINE __attribute__((always_inline)) inline
#else
#define COBGS_ALWAYS_INLINE inline
#endif

namespace cobgs {

// True when the AVX2 versions of the kernels should run (decided once per process).
inline bool cpu_use_avx2() {
#if COBGS_AVX2_CLONES
  static const bool use = [] {
    const char* off = std::getenv("COBGS_DISABLE_AVX2");
    if (off != nullptr && *off != '\0' && std::strcmp(off, "0") != 0) return false;
    __builtin_cpu_init();
    return __builtin_cpu_supports("avx2") != 0;
  }();
  return use;
#else
  return false;
#endif
}

}  // namespace cobgs
