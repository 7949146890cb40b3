// Run-time choice of the instruction set for the hot CPU loops.
//
// The extension is compiled for the baseline of the architecture (no -march=native, so a
// cached build runs on every CPU of that architecture). On x86-64 the per-tile kernels
// are compiled twice more, for AVX2 and for AVX-512 (function attributes target("avx2")
// and target("avx512f,avx512vl,...")), and the best one the CPU has is chosen at run
// time. The AVX-512 version keeps the kernels' 256-bit vectors (the same lanes) and gains
// 32 vector registers and mask registers: fewer instructions, not wider ones. All versions
// compute bit-identical results: the loops only use exactly rounded operations, and
// -ffp-contract=off forbids fused multiply-adds.
// COBGS_DISABLE_AVX2=1 forces the baseline version, COBGS_DISABLE_AVX512=1 forces AVX2
// at most (tests compare them).
#pragma once

#include <cstdlib>
#include <cstring>

#if (defined(__GNUC__) || defined(__clang__)) && (defined(__x86_64__) || defined(__i386__))
#define COBGS_AVX2_CLONES 1
#define COBGS_TARGET_AVX2 __attribute__((target("avx2")))
#define COBGS_TARGET_AVX512 \
  __attribute__((target("avx2,avx512f,avx512vl,avx512dq,avx512bw")))
#else
#define COBGS_AVX2_CLONES 0
#define COBGS_TARGET_AVX2
#define COBGS_TARGET_AVX512
#endif

#if defined(__GNUC__) || defined(__clang__)
#define COBGS_ALWAYS_INLINE __attribute__((always_inline)) inline
#else
#define COBGS_ALWAYS_INLINE inline
#endif

namespace cobgs {

enum class CpuIsa { kBase = 0, kAvx2 = 1, kAvx512 = 2 };

inline bool env_flag(const char* name) {
  const char* v = std::getenv(name);
  return v != nullptr && *v != '\0' && std::strcmp(v, "0") != 0;
}

// The instruction set the kernels use in this process (decided once).
inline CpuIsa cpu_isa() {
#if COBGS_AVX2_CLONES
  static const CpuIsa isa = [] {
    if (env_flag("COBGS_DISABLE_AVX2")) return CpuIsa::kBase;
    __builtin_cpu_init();
    if (!__builtin_cpu_supports("avx2")) return CpuIsa::kBase;
    if (!env_flag("COBGS_DISABLE_AVX512") && __builtin_cpu_supports("avx512f") &&
        __builtin_cpu_supports("avx512vl") && __builtin_cpu_supports("avx512dq") &&
        __builtin_cpu_supports("avx512bw"))
      return CpuIsa::kAvx512;
    return CpuIsa::kAvx2;
  }();
  return isa;
#else
  return CpuIsa::kBase;
#endif
}

// The CPU fast path of the blending kernels (csrc/blend/fast_path.cpp): versions compiled
// with fused multiply-adds (COBGS_BEGIN_ISA_*_FAST in simd_cpu.h), used while the switch
// is on and the CPU has AVX2 and FMA. Off by default (the exact, bit-identical versions);
// COBGS_CPU_FAST=1 turns it on at load, cobgs::set_cpu_fast at run time (the fast recipe's
// training does, TrainConfig.fast_kernels).
bool cpu_fast_path();

inline bool cpu_has_fma() {
#if COBGS_AVX2_CLONES
  static const bool fma = [] {
    __builtin_cpu_init();
    return __builtin_cpu_supports("fma") != 0;
  }();
  return fma;
#else
  return false;
#endif
}

// True when an AVX2 (or better) version of the kernels runs.
inline bool cpu_use_avx2() { return cpu_isa() != CpuIsa::kBase; }

// `expr` (a function, or a call) from the version of a kernel for this process's
// instruction set: a kernel compiled per instruction set lives in the namespaces
// <prefix>_base, <prefix>_avx2 and <prefix>_avx512 (see csrc/common/simd_cpu.h).
#if COBGS_AVX2_CLONES
#define COBGS_ISA_DISPATCH(prefix, ...)                                  \
  (::cobgs::cpu_isa() == ::cobgs::CpuIsa::kAvx512 ? prefix##_avx512::__VA_ARGS__ \
   : ::cobgs::cpu_isa() == ::cobgs::CpuIsa::kAvx2 ? prefix##_avx2::__VA_ARGS__   \
                                                  : prefix##_base::__VA_ARGS__)
// COBGS_ISA_DISPATCH, or the fast version (<prefix>_avx2fast / <prefix>_avx512fast) while
// the CPU fast path is on and the CPU can run it.
#define COBGS_ISA_DISPATCH_FAST(prefix, ...)                                          \
  ((::cobgs::cpu_fast_path() && ::cobgs::cpu_use_avx2() && ::cobgs::cpu_has_fma())   \
       ? (::cobgs::cpu_isa() == ::cobgs::CpuIsa::kAvx512 ? prefix##_avx512fast::__VA_ARGS__ \
                                                         : prefix##_avx2fast::__VA_ARGS__)  \
       : COBGS_ISA_DISPATCH(prefix, __VA_ARGS__))
#else
#define COBGS_ISA_DISPATCH(prefix, ...) (prefix##_base::__VA_ARGS__)
#define COBGS_ISA_DISPATCH_FAST(prefix, ...) (prefix##_base::__VA_ARGS__)
#endif

}  // namespace cobgs
