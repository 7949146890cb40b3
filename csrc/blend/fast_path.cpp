// The CUDA blending passes' path switch (blend_cuda.cuh, "the fast path"): the fast path is
// the default since a GPU run verified it (docs/benchmarks/cuda_h100.md, issue 49);
// COBGS_CUDA_EXACT=1 in the environment selects the exact path at load, cobgs::set_cuda_fast
// changes it at run time (the tests compare both paths in one process). A CPU-only build has
// the switch too, and cuda_fast_path() is then never read.
//
// The CPU blending kernels' switch (cpu_isa.h, COBGS_ISA_DISPATCH_FAST): off by default;
// COBGS_CPU_FAST=1 in the environment turns it on at load, cobgs::set_cpu_fast at run time
// (TrainConfig.fast_kernels: the training steps only).
#include <torch/library.h>

#include <atomic>

#include "../common/cpu_isa.h"  // env_flag

namespace cobgs {
namespace {

std::atomic<bool>& flag() {  // fast unless COBGS_CUDA_EXACT is set (not "" / "0")
  static std::atomic<bool> f{!env_flag("COBGS_CUDA_EXACT")};
  return f;
}

std::atomic<bool>& cpu_flag() {  // exact unless COBGS_CPU_FAST is set (not "" / "0")
  static std::atomic<bool> f{env_flag("COBGS_CPU_FAST")};
  return f;
}

// The previous setting, for the Python context managers to restore.
bool set_cuda_fast(bool on) { return flag().exchange(on); }
bool get_cuda_fast() { return flag().load(); }
bool set_cpu_fast(bool on) { return cpu_flag().exchange(on); }
bool get_cpu_fast() { return cpu_flag().load(); }

}  // namespace

bool cuda_fast_path() { return flag().load(std::memory_order_relaxed); }

bool cpu_fast_path() { return cpu_flag().load(std::memory_order_relaxed); }

TORCH_LIBRARY_FRAGMENT(cobgs, m) {
  m.def("set_cuda_fast(bool on) -> bool", &set_cuda_fast);
  m.def("get_cuda_fast() -> bool", &get_cuda_fast);
  m.def("set_cpu_fast(bool on) -> bool", &set_cpu_fast);
  m.def("get_cpu_fast() -> bool", &get_cpu_fast);
}

}  // namespace cobgs
