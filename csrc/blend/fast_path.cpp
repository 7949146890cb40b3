// The CUDA blending passes' path switch (blend_cuda.cuh, "the fast path"): off by default,
// COBGS_CUDA_FAST=1 in the environment turns it on at load, cobgs::set_cuda_fast changes it
// at run time (tests compare both paths in one process). A CPU-only build has the switch
// too: the CPU kernels have one path, and cuda_fast_path() is then never read.
#include <torch/library.h>

#include <atomic>
#include <cstdlib>
#include <cstring>

namespace cobgs {
namespace {

bool from_env() {
  const char* v = std::getenv("COBGS_CUDA_FAST");
  return v != nullptr && std::strcmp(v, "") != 0 && std::strcmp(v, "0") != 0;
}

std::atomic<bool>& flag() {
  static std::atomic<bool> f{from_env()};
  return f;
}

bool set_cuda_fast(bool on) {
  return flag().exchange(on);  // the previous setting
}

bool get_cuda_fast() { return flag().load(); }

}  // namespace

bool cuda_fast_path() { return flag().load(std::memory_order_relaxed); }

TORCH_LIBRARY_FRAGMENT(cobgs, m) {
  m.def("set_cuda_fast(bool on) -> bool", &set_cuda_fast);
  m.def("get_cuda_fast() -> bool", &get_cuda_fast);
}

}  // namespace cobgs
