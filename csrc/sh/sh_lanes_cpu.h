// The per-Gaussian loops of the `sh_colors` op family, written once and compiled once per
// instruction set: included (no include guard) inside a namespace of sh_cpu.cpp between
// COBGS_BEGIN_ISA_* / COBGS_END_ISA (see csrc/common/simd_cpu.h). The training case
// (float32, RGB, degree 3, 15 higher coefficients) runs 8 Gaussians per step in lane
// vectors through the lane-generic formulas of csrc/common/sh_math.h, their coefficients
// moved between memory and lanes by 8x8 transposes; every lane is bit-identical to the
// one-Gaussian evaluation, which serves the other cases and the remainders.

// The lane path: float32, 3 channels, degree 3, exactly 15 higher coefficients (45 floats
// per Gaussian).
constexpr int kRow = 45;

template <typename V>
inline V gather3(const float* base, int field) {
  V v;
  for (int k = 0; k < simd::kLanes; ++k) v[k] = base[3 * k + field];
  return v;
}

template <typename V>
inline void scatter3(float* base, int field, const V& v) {
  for (int k = 0; k < simd::kLanes; ++k) base[3 * k + field] = v[k];
}

// e[j] (j < 45) = float j of the 8 rows of 45 floats at src, lane r from row r.
template <typename V>
inline void load_rows45(const float* src, V e[48]) {
  for (int c = 0; c < 6; ++c) {
    V rows[8];
    for (int r = 0; r < 8; ++r) {
      if (c == 5 && r == 7) {  // the last row's tail: read nothing past the block
        rows[r] = V{};
        std::memcpy(&rows[r], src + kRow * r + 40, 5 * sizeof(float));
      } else {  // (rows 0-6 read 3 floats of the next row: ignored)
        rows[r] = simd::load<V>(src + kRow * r + 8 * c);
      }
    }
    simd::transpose8(rows);
    for (int q = 0; q < 8; ++q) e[8 * c + q] = rows[q];
  }
}

// The inverse: rows of 45 floats at dst from e[0..45).
template <typename V>
inline void store_rows45(float* dst, const V e[48]) {
  // The last 8-float column first: rows 0-6 spill 3 floats into the next row, which the
  // first column's stores then overwrite; the last row writes its 5 floats only.
  for (int c : {5, 0, 1, 2, 3, 4}) {
    V rows[8];
    for (int q = 0; q < 8; ++q) rows[q] = e[8 * c + q];
    simd::transpose8(rows);
    for (int r = 0; r < 8; ++r) {
      if (c == 5 && r == 7)
        std::memcpy(dst + kRow * r + 40, &rows[r], 5 * sizeof(float));
      else
        simd::store(dst + kRow * r + 8 * c, rows[r]);
    }
  }
}

// The three fields of 8 consecutive [N, 3] rows, one lane vector per field.
template <typename V>
inline void gather3x3(const float* base, V out[3]) {
  for (int f = 0; f < 3; ++f) out[f] = gather3<V>(base, f);
}

// What both passes evaluate first for the 8 Gaussians at i: the view direction, the
// basis, and the coefficients in lanes.
struct LaneInputs {
  typedef simd::Lanes<float>::V V;
  V dir[3], norm, nc, Y[sh::kMaxCoeffs], c0[3], cn[48];
};

template <typename Args>
inline void load_lane_inputs(const Args& a, int64_t i, LaneInputs& in) {
  LaneInputs::V m[3];
  gather3x3(a.means + 3 * i, m);
  sh::view_direction(m, a.center, in.dir, in.norm, in.nc);
  sh::basis(3, in.dir[0], in.dir[1], in.dir[2], in.Y);
  gather3x3(a.sh0 + 3 * i, in.c0);
  load_rows45(a.shN + kRow * i, in.cn);
}

template <typename Args>
inline bool lane_path(const Args& a) {
  return a.C == 3 && a.degree == 3 && a.M == 15;
}

// Gaussians [i0, i1).
template <typename T>
void sh_forward_range(const ShArgs<T>& a, int64_t i0, int64_t i1) {
  int64_t i = i0;
  if constexpr (std::is_same_v<T, float>) {
    if (lane_path(a)) {
      for (; i + simd::kLanes <= i1; i += simd::kLanes) {
        LaneInputs in;
        load_lane_inputs(a, i, in);
        simd::Lanes<float>::V v[3];
        sh::colour_sum(3, 16, in.Y, in.c0, in.cn, v);
        for (int ch = 0; ch < 3; ++ch) scatter3(a.out + 3 * i, ch, sh::clamp_colour(v[ch]));
      }
    }
  }
  if (a.C == 3 && a.degree == 3) {
    for (; i < i1; ++i) sh_forward_one<T, 3, 3>(a, i);
  } else {
    for (; i < i1; ++i) sh_forward_one<T, 0, -1>(a, i);
  }
}

template <typename T>
void sh_backward_range(const ShBwdArgs<T>& a, int64_t i0, int64_t i1) {
  int64_t i = i0;
  if constexpr (std::is_same_v<T, float>) {
    if (lane_path(a)) {
      using V = simd::Lanes<float>::V;
      using M = simd::Lanes<float>::M;
      const V zero{};
      for (; i + simd::kLanes <= i1; i += simd::kLanes) {
        V vcol[3];
        gather3x3(a.v_col + 3 * i, vcol);
        const M active = (vcol[0] != zero) | (vcol[1] != zero) | (vcol[2] != zero);
        float* g0 = a.v_sh0 + 3 * i;
        float* gn = a.v_shN + kRow * i;
        float* vm = a.v_means + 3 * i;
        if (!math::lane_any(active)) {
          std::fill(g0, g0 + 3 * simd::kLanes, 0.0f);
          std::fill(gn, gn + kRow * simd::kLanes, 0.0f);
          std::fill(vm, vm + 3 * simd::kLanes, 0.0f);
          continue;
        }
        LaneInputs in;
        load_lane_inputs(a, i, in);
        V vg0[3], vgn[48], vmean[3];
        sh::colour_vjp(3, 3, in.Y, in.dir, in.norm, in.nc, in.c0, in.cn, vcol, vg0, vgn, vmean);
        // Lanes without any colour gradient: zeros, as sh_backward_one writes.
        for (int e = 0; e < kRow; ++e) vgn[e] = active ? vgn[e] : zero;
        for (int ch = 0; ch < 3; ++ch) {
          scatter3(g0, ch, active ? vg0[ch] : zero);
          scatter3(vm, ch, active ? vmean[ch] : zero);
        }
        store_rows45(gn, vgn);
      }
    }
  }
  if (a.C == 3 && a.degree == 3) {
    for (; i < i1; ++i) sh_backward_one<T, 3, 3>(a, i);
  } else {
    for (; i < i1; ++i) sh_backward_one<T, 0, -1>(a, i);
  }
}
