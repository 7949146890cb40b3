// OpenMP helpers for the CPU kernels. Parallel regions use the thread count PyTorch is
// set to (torch.set_num_threads), so one knob controls ATen and these kernels. The
// extension links the same libgomp as torch (soname libgomp.so.1), so there is a
// single OpenMP runtime in the process.
#pragma once

#include <ATen/Parallel.h>

#include <algorithm>
#include <cstdint>

namespace cobgs {

inline int cpu_threads() { return std::max(1, at::get_num_threads()); }

// fn(i0, i1) over [0, n) in consecutive ranges of `chunk` items, split statically between
// the threads: which items share a call does not depend on the thread count.
template <typename F>
void parallel_ranges(int64_t n, int64_t chunk, const F& fn) {
  const int64_t chunks = (n + chunk - 1) / chunk;
#pragma omp parallel for schedule(static) num_threads(cpu_threads())
  for (int64_t c = 0; c < chunks; ++c) fn(c * chunk, std::min(n, (c + 1) * chunk));
}

}  // namespace cobgs
