// The per-Gaussian loops of the `project` op family, written once and compiled once per
// instruction set: included (no include guard) inside a namespace of project_cpu.cpp
// between COBGS_BEGIN_ISA_* / COBGS_END_ISA with COBGS_ISA_LEVEL set (see
// csrc/common/simd_cpu.h). float32 runs 8 Gaussians per step in lane vectors through the
// lane-generic formulas of csrc/common/gs_math.h (every lane bit-identical to the scalar
// evaluation); the last n % 8 Gaussians, and float64, run one at a time through the same
// formulas.

template <typename T>
inline void project_one(const ProjArgs<T>& a, int64_t i) {
  const auto g = math::load_gaussian<T>(a.means + 3 * i, a.quats + 4 * i, a.scales + 3 * i);
  const math::Projection<T> p = math::project_gaussian<T>(a.cam, g, a.near);
  a.means2d[2 * i] = p.mx;
  a.means2d[2 * i + 1] = p.my;
  a.conics[3 * i] = p.ca;
  a.conics[3 * i + 1] = p.cb;
  a.conics[3 * i + 2] = p.cc;
  a.depths[i] = p.depth;
  a.radii[i] = static_cast<int32_t>(p.radius);
}

template <typename T>
inline void project_bwd_one(const ProjBwdArgs<T>& a, int64_t i) {
  const T vmx = a.v_means2d[2 * i], vmy = a.v_means2d[2 * i + 1];
  const T vca = a.v_conics[3 * i], vcb = a.v_conics[3 * i + 1], vcc = a.v_conics[3 * i + 2];
  const T vd = a.v_depths[i];
  T* om = a.v_means + 3 * i;
  T* oq = a.v_quats + 4 * i;
  T* os = a.v_scales + 3 * i;
  // Culled, or no gradient received (e.g. behind opaque pixels everywhere in this
  // view): every gradient is zero, no recomputation.
  if (a.radii[i] <= 0 || (vmx == T(0) && vmy == T(0) && vca == T(0) && vcb == T(0) &&
                          vcc == T(0) && vd == T(0))) {
    std::fill(om, om + 3, T(0));
    std::fill(oq, oq + 4, T(0));
    std::fill(os, os + 3, T(0));
    return;
  }
  const auto g = math::load_gaussian<T>(a.means + 3 * i, a.quats + 4 * i, a.scales + 3 * i);
  const math::GaussianGrad<T> r =
      math::project_gaussian_vjp<T>(a.cam, g, vmx, vmy, vca, vcb, vcc, vd);
  // 0 + x (as accumulating into zeros would): -0 becomes +0.
  om[0] = T(0) + r.mean.x;
  om[1] = T(0) + r.mean.y;
  om[2] = T(0) + r.mean.z;
  for (int k = 0; k < 4; ++k) oq[k] = T(0) + r.quat[k];
  for (int k = 0; k < 3; ++k) os[k] = T(0) + r.scale[k];
}

// Lane vectors of 8 consecutive Gaussians' fields from an [N, stride] array.
template <typename V, typename T>
inline V gather_field(const T* base, int stride, int field) {
  V v;
  for (int k = 0; k < simd::kLanes; ++k) v[k] = base[k * stride + field];
  return v;
}

template <typename V, typename T>
inline void scatter_field(T* base, int stride, int field, const V& v) {
  for (int k = 0; k < simd::kLanes; ++k) base[k * stride + field] = v[k];
}

template <typename V, typename T>
inline math::GaussianIn<V> gather_gaussians(const T* means, const T* quats, const T* scales) {
  math::GaussianIn<V> g;
  g.mean = {gather_field<V>(means, 3, 0), gather_field<V>(means, 3, 1),
            gather_field<V>(means, 3, 2)};
  for (int k = 0; k < 4; ++k) g.quat[k] = gather_field<V>(quats, 4, k);
  for (int k = 0; k < 3; ++k) g.scale[k] = gather_field<V>(scales, 3, k);
  return g;
}

// Gaussians [i0, i1).
template <typename T>
void project_range(const ProjArgs<T>& a, int64_t i0, int64_t i1) {
  int64_t i = i0;
  if constexpr (std::is_same_v<T, float>) {
    using V = simd::Lanes<float>::V;
    for (; i + simd::kLanes <= i1; i += simd::kLanes) {
      const auto g = gather_gaussians<V>(a.means + 3 * i, a.quats + 4 * i, a.scales + 3 * i);
      const math::Projection<V> p = math::project_gaussian<V>(a.cam, g, a.near);
      scatter_field(a.means2d + 2 * i, 2, 0, p.mx);
      scatter_field(a.means2d + 2 * i, 2, 1, p.my);
      scatter_field(a.conics + 3 * i, 3, 0, p.ca);
      scatter_field(a.conics + 3 * i, 3, 1, p.cb);
      scatter_field(a.conics + 3 * i, 3, 2, p.cc);
      simd::store(a.depths + i, p.depth);
      simd::store(a.radii + i, __builtin_convertvector(p.radius, simd::VI));
    }
  }
  for (; i < i1; ++i) project_one(a, i);
}

template <typename T>
void project_bwd_range(const ProjBwdArgs<T>& a, int64_t i0, int64_t i1) {
  int64_t i = i0;
  if constexpr (std::is_same_v<T, float>) {
    using V = simd::Lanes<float>::V;
    using M = simd::Lanes<float>::M;
    const V zero{};
    for (; i + simd::kLanes <= i1; i += simd::kLanes) {
      const V vmx = gather_field<V>(a.v_means2d + 2 * i, 2, 0);
      const V vmy = gather_field<V>(a.v_means2d + 2 * i, 2, 1);
      const V vca = gather_field<V>(a.v_conics + 3 * i, 3, 0);
      const V vcb = gather_field<V>(a.v_conics + 3 * i, 3, 1);
      const V vcc = gather_field<V>(a.v_conics + 3 * i, 3, 2);
      const V vd = simd::load<V>(a.v_depths + i);
      const M active = (simd::load<simd::VI>(a.radii + i) > 0) &
                       ((vmx != zero) | (vmy != zero) | (vca != zero) | (vcb != zero) |
                        (vcc != zero) | (vd != zero));
      T* om = a.v_means + 3 * i;
      T* oq = a.v_quats + 4 * i;
      T* os = a.v_scales + 3 * i;
      if (!math::lane_any(active)) {
        std::fill(om, om + 3 * simd::kLanes, T(0));
        std::fill(oq, oq + 4 * simd::kLanes, T(0));
        std::fill(os, os + 3 * simd::kLanes, T(0));
        continue;
      }
      const auto g = gather_gaussians<V>(a.means + 3 * i, a.quats + 4 * i, a.scales + 3 * i);
      const math::GaussianGrad<V> r =
          math::project_gaussian_vjp<V>(a.cam, g, vmx, vmy, vca, vcb, vcc, vd);
      // As project_bwd_one: 0 + x where active, 0 elsewhere.
      auto put = [&](T* base, int stride, int field, const V& v) {
        scatter_field(base, stride, field, active ? zero + v : zero);
      };
      put(om, 3, 0, r.mean.x);
      put(om, 3, 1, r.mean.y);
      put(om, 3, 2, r.mean.z);
      for (int k = 0; k < 4; ++k) put(oq, 4, k, r.quat[k]);
      for (int k = 0; k < 3; ++k) put(os, 3, k, r.scale[k]);
    }
  }
  for (; i < i1; ++i) project_bwd_one(a, i);
}
