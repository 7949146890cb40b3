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
#include <cstdlib>
#include <cstring>

namespace cobgs {
namespace {

bool from_env() {  // fast unless COBGS_CUDA_EXACT is set to something other than "" / "0"
  const char* v = std::getenv("COBGS_CUDA_EXACT");
  return v == nullptr || std::strcmp(v, "") == 0 || std::strcmp(v, "0") == 0;
}

std::atomic<bool>& flag() {
  static std::atomic<bool> f{from_env()};
  return f;
}

bool set_cuda_fast(bool on) {
  return flag().exchange(on);  // the previous setting
}

bool get_cuda_fast() { return flag().load(); }

bool cpu_from_env() {  // exact unless COBGS_CPU_FAST is set to something other than "" / "0"
  const char* v = std::getenv("COBGS_CPU_FAST");
  return v != nullptr && std::strcmp(v, "") != 0 && std::strcmp(v, "0") != 0;
}

std::atomic<bool>& cpu_flag() {
  static std::atomic<bool> f{cpu_from_env()};
  return f;
}

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
