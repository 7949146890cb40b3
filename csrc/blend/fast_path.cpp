// The CUDA blending passes' path switch (blend_cuda.cuh, "the fast path"): the fast path is
// the default since a GPU run verified it (docs/benchmarks/cuda_h100.md, issue 49);
// COBGS_CUDA_EXACT=1 in the environment selects the exact path at load, cobgs::set_cuda_fast
// changes it at run time (the tests compare both paths in one process). A CPU-only build has
// the switch too: the CPU kernels have one path, and cuda_fast_path() is then never read.
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

}  // namespace

bool cuda_fast_path() { return flag().load(std::memory_order_relaxed); }

TORCH_LIBRARY_FRAGMENT(cobgs, m) {
  m.def("set_cuda_fast(bool on) -> bool", &set_cuda_fast);
  m.def("get_cuda_fast() -> bool", &get_cuda_fast);
}

}  // namespace cobgs
