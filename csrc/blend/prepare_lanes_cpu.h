// blend's per-Gaussian records (GaussPrep, see blend_tile_cpu.h) for a range of
// Gaussians, written once and compiled once per instruction set: included (no include
// guard) inside a namespace of prepare_cpu.cpp between COBGS_BEGIN_ISA_* / COBGS_END_ISA.
// 8 Gaussians at a time in lane vectors of doubles through math::make_blend_bound (each
// lane bit-identical to the one-Gaussian evaluation), the rest one at a time.

template <typename T>
void prepare_range(const T* m2, const T* co, const T* op, int64_t i0, int64_t i1,
                   GaussPrep<T>* prep) {
  const double eps = prep_eps<T>();
  using VT = typename simd::Lanes<T>::V;
  using VD = simd::Lanes<double>::V;
  int64_t i = i0;
  for (; i + simd::kLanes <= i1; i += simd::kLanes) {
    VT f[6];  // mx, my, ca, cb, cc, o of 8 Gaussians
    for (int k = 0; k < simd::kLanes; ++k) {
      f[0][k] = m2[2 * (i + k)];
      f[1][k] = m2[2 * (i + k) + 1];
      f[2][k] = co[3 * (i + k)];
      f[3][k] = co[3 * (i + k) + 1];
      f[4][k] = co[3 * (i + k) + 2];
    }
    f[5] = simd::load<VT>(op + i);
    VD d[6];
    for (int j = 0; j < 6; ++j) d[j] = __builtin_convertvector(f[j], VD);
    const math::BlendBound<VD> bb =
        math::make_blend_bound<VD>(d[0], d[1], d[2], d[3], d[4], d[5], eps);
    for (int k = 0; k < simd::kLanes; ++k)
      write_prep(prep + i + k, f[0][k], f[1][k], f[2][k], f[3][k], f[4][k], f[5][k],
                 bb.power_reject[k], bb.x0[k], bb.x1[k], bb.y0[k], bb.y1[k]);
  }
  for (; i < i1; ++i) prepare_one(m2, co, op, i, prep + i);
}
