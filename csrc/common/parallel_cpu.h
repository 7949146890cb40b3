// OpenMP helpers for the CPU kernels. Parallel regions use the thread count PyTorch is
// set to (torch.set_num_threads), so one knob controls ATen and these kernels. The
// extension links the same libgomp as torch (soname libgomp.so.1), so there is a
// single OpenMP runtime in the process.
#pragma once

#include <ATen/Parallel.h>

#include <algorithm>

namespace cobgs {

inline int cpu_threads() { return std::max(1, at::get_num_threads()); }

}  // namespace cobgs
