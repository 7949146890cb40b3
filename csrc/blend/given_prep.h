// The `prep` argument of blend / blend_bwd (the records of bin_tiles_tight), checked the
// same way by both backends.
#pragma once

#include <torch/types.h>

#include <optional>

#include "gauss_prep.h"

namespace cobgs {
namespace blend_detail {

// The records `prepare` would compute, when the caller already has them: the `prep`
// output of `bin_tiles_tight` for the same means2d / conics / opacities (a [N, record
// size] uint8 tensor). Returns null when absent (the pass then runs `prepare` itself).
// Only the size is checked: records from other inputs give wrong pixels, never
// out-of-range accesses (every box is clipped to the tile it is used in).
template <typename T>
const GaussPrep<T>* given_prep(const std::optional<at::Tensor>& prep,
                               const at::Tensor& means2d) {
  if (!prep.has_value()) return nullptr;
  const int64_t n = means2d.size(0);
  const at::Tensor& p = *prep;
  const int64_t record = static_cast<int64_t>(sizeof(GaussPrep<T>));
  TORCH_CHECK(p.device() == means2d.device() && p.is_contiguous() &&
                  p.scalar_type() == at::kByte && p.dim() == 2 && p.size(0) == n &&
                  p.size(1) == record,
              "prep must be the prep output of bin_tiles_tight for these inputs: a contiguous "
              "uint8 tensor on ", means2d.device(), " of shape [", n, ", ", record, "] for ",
              sizeof(T) == 4 ? "float32" : "float64", " inputs, got ", p.scalar_type(),
              " of shape ", p.sizes(), " on ", p.device());
  TORCH_CHECK(reinterpret_cast<uintptr_t>(p.data_ptr()) % alignof(GaussPrep<T>) == 0,
              "prep must be aligned to ", alignof(GaussPrep<T>), " bytes (a fresh tensor from "
              "bin_tiles_tight, not a view)");
  return reinterpret_cast<const GaussPrep<T>*>(p.data_ptr<uint8_t>());
}

}  // namespace blend_detail
}  // namespace cobgs
