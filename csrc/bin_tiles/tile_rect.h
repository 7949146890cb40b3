// The tile rectangle of a Gaussian, shared by the CPU and CUDA binning kernels: the tiles
// its 3-sigma square touches (cobgs/render/reference.py, tile_rects), optionally narrowed to the
// tiles that hold a pixel of its α >= 1/255 box (the `prep` record).
#pragma once

#include <cmath>
#include <cstdint>

#include "../common/gs_math.h"

namespace cobgs {
namespace bin_detail {

struct Rect {
  int32_t x0, y0, x1, y1;
};

// Tiles [floor((m - r) / 16), ceil((m + r) / 16)) on each axis, clamped to the grid.
template <typename T>
HOST_DEVICE inline Rect tile_rect(T mx, T my, int32_t radius, int tiles_x, int tiles_y) {
  const T r = static_cast<T>(radius);
  const T ts = static_cast<T>(math::kTileSize);
  auto clampi = [](T v, int hi) {
    return static_cast<int32_t>(v < T(0) ? T(0) : (v > T(hi) ? T(hi) : v));
  };
  return {clampi(std::floor((mx - r) / ts), tiles_x), clampi(std::floor((my - r) / ts), tiles_y),
          clampi(std::ceil((mx + r) / ts), tiles_x), clampi(std::ceil((my + r) / ts), tiles_y)};
}

// `rc` narrowed to the tiles that hold a pixel of the box [x0, x1) x [y0, y1) (pixel
// indices, possibly far outside the image; empty when x0 >= x1 or y0 >= y1).
HOST_DEVICE inline Rect narrow_to_box(Rect rc, int64_t x0, int64_t x1, int64_t y0, int64_t y1) {
  const int64_t ts = math::kTileSize;
  auto floor_div = [ts](int64_t v) { return v >= 0 ? v / ts : -((-v + ts - 1) / ts); };
  if (x0 >= x1 || y0 >= y1) return {rc.x0, rc.y0, rc.x0, rc.y0};
  // Tiles floor(x0 / 16) .. floor((x1 - 1) / 16), clamped into rc.
  auto lo = [](int32_t a, int64_t b) { return static_cast<int32_t>(b > a ? b : a); };
  auto hi = [](int32_t a, int64_t b) { return static_cast<int32_t>(b < a ? b : a); };
  Rect out{lo(rc.x0, floor_div(x0)), lo(rc.y0, floor_div(y0)), hi(rc.x1, floor_div(x1 - 1) + 1),
           hi(rc.y1, floor_div(y1 - 1) + 1)};
  if (out.x1 < out.x0) out.x1 = out.x0;
  if (out.y1 < out.y0) out.y1 = out.y0;
  return out;
}

// Unsigned keys whose order is the order of the (positive, finite) depths.
HOST_DEVICE inline uint32_t depth_key(float d) {
  uint32_t k;
  memcpy(&k, &d, sizeof(k));
  return k;
}
HOST_DEVICE inline uint64_t depth_key(double d) {
  uint64_t k;
  memcpy(&k, &d, sizeof(k));
  return k;
}

}  // namespace bin_detail
}  // namespace cobgs
