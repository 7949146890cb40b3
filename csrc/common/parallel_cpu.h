// OpenMP helpers for the CPU kernels. Parallel regions use the thread count PyTorch is
// set to (torch.set_num_threads), so one knob controls ATen and these kernels. The
// extension links the same libgomp as torch (soname libgomp.so.1), so there is a
// single OpenMP runtime in the process.
#pragma once

#include <ATen/Parallel.h>

#include <algorithm>
#include <cstdint>
#include <utility>

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

// Threads for n items split into one contiguous range per thread, each of at least
// `grain` items (a parallel region costs more than a small range saves); at least 1.
inline int range_threads(int64_t n, int64_t grain) {
  return static_cast<int>(std::max<int64_t>(1, std::min<int64_t>(cpu_threads(), n / grain)));
}

// The range [first, second) of [0, n) that thread `tid` of `nt` takes; the ranges are in
// thread order, so results written range after range come out in index order.
inline std::pair<int64_t, int64_t> thread_range(int64_t n, int tid, int nt) {
  return {n * tid / nt, n * (tid + 1) / nt};
}

}  // namespace cobgs
