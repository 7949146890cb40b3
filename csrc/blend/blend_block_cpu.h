// Per-block math shared by the forward and backward tile kernels. Included (no include
// guard) inside each instruction-set namespace of both kernels, right after
// simd_isa_cpu.h: one definition, so the backward recomputes the forward's decisions bit
// for bit (with -ffp-contract=off the operations round identically wherever inlined).

// The Gaussian's exponent over one block of pixels of a row:
// power = -0.5 (a dx² + c dy²) - b dx dy, with c dy² computed once per row.
template <typename T, typename V, typename G>
inline V block_power(const G& g, const V& px_centre, T dy, T cc_dy_dy) {
  const V dx = px_centre - g.mx;
  return T(-0.5) * (g.ca * dx * dx + cc_dy_dy) - g.cb * dx * dy;
}
