// blend's per-Gaussian records: the range loop of prepare_lanes_cpu.h once per
// instruction set, and the run-time choice (csrc/common/cpu_isa.h).
#include <cstring>
#include <limits>

#include "../common/cpu_isa.h"
#include "../common/simd_cpu.h"
#include "blend_tile_cpu.h"

namespace cobgs {
namespace blend_detail {

namespace prepare_base {
#define COBGS_ISA_LEVEL 0
#include "prepare_lanes_cpu.h"
#undef COBGS_ISA_LEVEL
}  // namespace prepare_base
#if COBGS_AVX2_CLONES
COBGS_BEGIN_ISA_AVX2
namespace prepare_avx2 {
#define COBGS_ISA_LEVEL 1
#include "prepare_lanes_cpu.h"
#undef COBGS_ISA_LEVEL
}  // namespace prepare_avx2
COBGS_END_ISA
COBGS_BEGIN_ISA_AVX512
namespace prepare_avx512 {
#define COBGS_ISA_LEVEL 2
#include "prepare_lanes_cpu.h"
#undef COBGS_ISA_LEVEL
}  // namespace prepare_avx512
COBGS_END_ISA
#endif

template <typename T>
PrepareRangeFn<T> prepare_range_fn() {
  return COBGS_ISA_DISPATCH(prepare, prepare_range<T>);
}

template PrepareRangeFn<float> prepare_range_fn<float>();
template PrepareRangeFn<double> prepare_range_fn<double>();

}  // namespace blend_detail
}  // namespace cobgs
