// The per-Gaussian record of the blending passes (`prep`), shared by the CPU and the CUDA
// kernels so that `bin_tiles_tight` returns the same bytes on both: the 2D mean, conic and
// opacity, the power below which α < 1/255 for sure, and the pixel box outside which no
// pixel can reach α >= 1/255 (math::make_blend_bound). The exact per-pixel test always
// follows; the record only prunes.
#pragma once

#include <cstdint>
#include <cstring>
#include <limits>

#include "../common/gs_math.h"

namespace cobgs {
namespace blend_detail {

// Compact and (float32: 44 bytes) aligned to a cache line, so that a tile-list entry
// costs one line (entries of a tile point to Gaussians all over memory).
template <typename T>
struct alignas(sizeof(T) == 4 ? 64 : 16) GaussPrep {
  T mx, my, ca, cb, cc, o;
  T power_reject;          // power < this ⇒ α < 1/255 for sure (checked before exp)
  int32_t x0, x1, y0, y1;  // pixel box that can get α >= 1/255; empty if none can
};

// Writes one record from its fields and the bound (computed in double).
template <typename T>
HOST_DEVICE inline void write_prep(GaussPrep<T>* dst, T mx, T my, T ca, T cb, T cc, T o,
                                   double power_reject, double x0, double x1, double y0,
                                   double y1) {
  GaussPrep<T> g;
  // Zeroed first, tail padding included: bin_tiles_tight returns these records as a
  // tensor, whose bytes must not depend on what the memory held before.
  memset(&g, 0, sizeof(g));
  g.mx = mx;
  g.my = my;
  g.ca = ca;
  g.cb = cb;
  g.cc = cc;
  g.o = o;
  g.power_reject = static_cast<T>(power_reject);
  g.x0 = static_cast<int32_t>(x0);
  g.x1 = static_cast<int32_t>(x1);
  g.y0 = static_cast<int32_t>(y0);
  g.y1 = static_cast<int32_t>(y1);
  *dst = g;
}

// The unit roundoff of T, the precision pixel_power is evaluated in.
template <typename T>
HOST_DEVICE constexpr double prep_eps() {
  return sizeof(T) == 4 ? 5.9604644775390625e-08 : 1.1102230246251565e-16;
}

// The record of Gaussian i (one at a time; the CPU also has an 8-lane version of the same
// formulas, csrc/blend/prepare_lanes_cpu.h).
template <typename T>
HOST_DEVICE inline void prepare_one(const T* m2, const T* co, const T* op, int64_t i,
                                    GaussPrep<T>* dst) {
  const T mx = m2[2 * i], my = m2[2 * i + 1];
  const T ca = co[3 * i], cb = co[3 * i + 1], cc = co[3 * i + 2], o = op[i];
  const math::BlendBound<double> bb =
      math::make_blend_bound<double>(mx, my, ca, cb, cc, o, prep_eps<T>());
  write_prep(dst, mx, my, ca, cb, cc, o, bb.power_reject, bb.x0, bb.x1, bb.y0, bb.y1);
}

}  // namespace blend_detail
}  // namespace cobgs
