// Input checks shared by the CPU and CUDA op implementations. Python validates user input
// with typed errors first (cobgs/render/rasterize.py); these guard direct torch.ops.cobgs.* calls
// so that a wrong tensor is an error naming it, never a crash. The shape / dtype checks of
// each op family are written once (in its header) against a reference tensor `ref`; each
// backend first checks that `ref` is on its kind of device.
#pragma once

#include <torch/types.h>

#include <vector>

#define COBGS_CHECK_CPU(x) \
  TORCH_CHECK((x).device().is_cpu(), #x " must be a CPU tensor, got ", (x).device())

#define COBGS_CHECK_CONTIGUOUS(x) TORCH_CHECK((x).is_contiguous(), #x " must be contiguous")

#define COBGS_CHECK_DTYPE(x, dtype)                                                      \
  TORCH_CHECK((x).scalar_type() == (dtype), #x " must have dtype ", (dtype), ", got ", \
              (x).scalar_type())

// Shape check; -1 entries match any size.
#define COBGS_CHECK_SHAPE(x, ...)                                                      \
  do {                                                                                 \
    const std::vector<int64_t> want_{__VA_ARGS__};                                     \
    bool ok_ = (x).dim() == static_cast<int64_t>(want_.size());                       \
    for (size_t i_ = 0; ok_ && i_ < want_.size(); ++i_)                                \
      ok_ = want_[i_] < 0 || (x).size(static_cast<int64_t>(i_)) == want_[i_];         \
    TORCH_CHECK(ok_, #x " must have shape ", c10::IntArrayRef(want_), " (-1 = any), got ", \
                (x).sizes());                                                          \
  } while (0)

#define COBGS_CHECK_INPUT(x) \
  COBGS_CHECK_CPU(x);        \
  COBGS_CHECK_CONTIGUOUS(x)

// x lies on the device of ref and is contiguous.
#define COBGS_CHECK_LIKE(x, ref)                                                          \
  TORCH_CHECK((x).device() == (ref).device(), #x " must be on ", (ref).device(),           \
              " (the device of " #ref "), got ", (x).device());                          \
  COBGS_CHECK_CONTIGUOUS(x)
