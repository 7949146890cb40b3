// The per-tile kernel of the backward blend, written once and compiled once per instruction set:
// included (no include guard) inside a namespace of blend_bwd_cpu.cpp between
// COBGS_BEGIN_ISA_* / COBGS_END_ISA with COBGS_ISA_LEVEL set (see csrc/common/simd_cpu.h).
// NC > 0 fixes the channel count at compile time (RGB: 3, one mask label: 1), so the
// per-channel loops unroll; NC = 0 reads it from the arguments.
#include "../common/simd_isa_cpu.h"

template <typename T, int NC>
void backward_tile(const BwdArgs<T>& a, int64_t tile, BwdScratch<T>& s) {
  using V = typename simd::Lanes<T>::V;
  using M = typename simd::Lanes<T>::M;
  using simd::VI;
  using simd::load;
  using simd::store;
  const V alpha_min = simd::splat<V>(T(math::kAlphaMin));
  const V alpha_max = simd::splat<V>(T(math::kAlphaMax));
  const V zero = simd::splat<V>(T(0)), one = simd::splat<V>(T(1));
  const int C = NC > 0 ? NC : a.C, S = a.S;
  const int64_t lo = a.off[tile], hi = a.off[tile + 1];
  if (lo == hi) return;
  const int x0 = int(tile % a.tiles_x) * kTileSize, y0 = int(tile / a.tiles_x) * kTileSize;
  const int x1 = std::min(x0 + kTileSize, a.width), y1 = std::min(y0 + kTileSize, a.height);
  // Pixels outside the image (edge tiles) are never blended (n_contrib 0) but do sit in
  // the blocks: give them finite state so masked lanes stay exactly zero.
  std::fill(s.last, s.last + kTilePixels, 0);
  std::fill(s.Tp, s.Tp + kTilePixels, T(1));
  std::fill(s.vtt, s.vtt + kTilePixels, T(0));
  std::fill(s.rest.begin(), s.rest.end(), T(0));
  std::fill(s.vcol.begin(), s.vcol.end(), T(0));
  int max_last = 0;
  int32_t block_last[kTileSize][2] = {};  // per row and block: the largest n_contrib
  for (int py = y0; py < y1; ++py)
    for (int px = x0; px < x1; ++px) {
      const int p = (py - y0) * kTileSize + (px - x0);
      const int64_t pix = int64_t(py) * a.width + px;
      s.Tp[p] = a.trans[pix];
      s.vtt[p] = a.v_trans[pix] * a.trans[pix];
      s.last[p] = a.n_contrib[pix];
      max_last = std::max(max_last, s.last[p]);
      int32_t& bl = block_last[py - y0][(px - x0) / simd::kLanes];
      bl = std::max(bl, s.last[p]);
      for (int c = 0; c < C; ++c) {
        s.rest[size_t(c) * kTilePixels + p] = a.bg[c];
        s.vcol[size_t(c) * kTilePixels + p] = a.v_image[pix * C + c];
      }
    }
  V px_centre[2];
  for (int b = 0; b < 2; ++b)
    for (int k = 0; k < simd::kLanes; ++k)
      px_centre[b][k] = T(x0 + b * simd::kLanes + k) + T(0.5);
  // Per-lane gradient sums of the current entry (all zero between entries).
  V acc_mx = zero, acc_my = zero, acc_ca = zero, acc_cb = zero, acc_cc = zero, acc_op = zero;
  T* acc_f = s.acc_f.data();
  // Entries behind every pixel's last contributor have nothing to do: zero slots.
  for (int64_t j = lo + max_last; j < hi; ++j)
    std::fill(a.slot_grad + a.slot[j] * S, a.slot_grad + a.slot[j] * S + S, T(0));

  for (int64_t rank = max_last - 1; rank >= 0; --rank) {
    const int64_t j = lo + rank;
    if (rank >= kPrefetchAhead) {
      const int32_t ahead = a.ids[j - kPrefetchAhead];
      COBGS_PREFETCH(&a.prep[ahead]);
      COBGS_PREFETCH(a.feat + int64_t(ahead) * C);
    }
    T* dst = a.slot_grad + a.slot[j] * S;
    const int32_t gi = a.ids[j];
    const GaussPrep<T> g = a.prep[gi];
    const int gx0 = std::max(x0, g.x0), gx1 = std::min(x1, g.x1);
    const int gy0 = std::max(y0, g.y0), gy1 = std::min(y1, g.y1);
    if (gx0 >= gx1 || gy0 >= gy1) {
      std::fill(dst, dst + S, T(0));
      continue;
    }
    const T* f = a.feat + int64_t(gi) * C;
    const int b0 = (gx0 - x0) / simd::kLanes, b1 = (gx1 - 1 - x0) / simd::kLanes;
    const int32_t rank32 = static_cast<int32_t>(rank);
    const VI rank_v = simd::splat<VI>(rank32);
    // Phase 1: exp and the blend mask of every block of the box (independent blocks, no
    // data-dependent branches: the out-of-order core overlaps their exp chains).
    int nblk = 0;
    for (int py = gy0; py < gy1; ++py) {
      const T dy = (T(py) + T(0.5)) - g.my;
      const T cc_dy_dy = g.cc * dy * dy;
      for (int b = b0; b <= b1; ++b) {
        // A block where this entry lies behind every pixel's last contributor.
        if (rank32 >= block_last[py - y0][b]) continue;
        const int p = (py - y0) * kTileSize + b * simd::kLanes;
        // Which pixels this Gaussian was blended into, and its α there (the forward's
        // decision, recomputed bit for bit).
        const V dx = px_centre[b] - g.mx;
        const V power = T(-0.5) * (g.ca * dx * dx + cc_dy_dy) - g.cb * dx * dy;
        const V gauss = gauss_exp(power);
        const V alpha = min_with(alpha_max, g.o * gauss);
        const M ok = simd::to_mask(rank_v < load<VI>(s.last + p), T(0)) & (power <= zero) &
                     (power >= g.power_reject) & (alpha >= alpha_min);
        store(s.blk_gauss + nblk * simd::kLanes, gauss);
        store(s.blk_ok + nblk * simd::kLanes, simd::to_i32(ok));
        s.blk_pix[nblk++] = p;
      }
    }
    // Phase 2: gradients of the blended pixels.
    bool entry_hit = false;  // the accumulators hold something (all zero otherwise)
    for (int i = 0; i < nblk; ++i) {
      const VI ok32 = load<VI>(s.blk_ok + i * simd::kLanes);
      if (!any(ok32)) continue;
      entry_hit = true;
      const int p = s.blk_pix[i];
      const M ok = simd::to_mask(ok32, T(0));
      const T dy = (T(y0 + p / kTileSize) + T(0.5)) - g.my;
      const V dx = px_centre[(p % kTileSize) / simd::kLanes] - g.mx;
      const V gauss = load<V>(s.blk_gauss + i * simd::kLanes);
      const V o_g = g.o * gauss;
      const V alpha = min_with(alpha_max, o_g);
      const V one_minus = one - alpha;
      const V t_after = load<V>(s.Tp + p);
      const V t_front = t_after / one_minus;  // T in front of this Gaussian
      store(s.Tp + p, ok ? t_front : t_after);
      // Per channel: dL/df = α T dL/dC, Σ_c (f_c - R_c) dL/dC_c, then R ← α f + (1 - α) R.
      V dot = zero;
      for (int c = 0; c < C; ++c) {
        const T fc = f[c];
        T* r = s.rest.data() + size_t(c) * kTilePixels + p;
        const V v_ok = ok ? load<V>(s.vcol.data() + size_t(c) * kTilePixels + p) : zero;
        const V rv = load<V>(r);
        T* af = acc_f + c * simd::kLanes;
        store(af, load<V>(af) + alpha * t_front * v_ok);
        dot += (fc - rv) * v_ok;
        store(r, ok ? alpha * fc + one_minus * rv : rv);
      }
      // dL/dα → opacity, conic and mean (no gradient where the 0.99 clamp is active);
      // a zero v_alpha makes every term below zero.
      const M ok_grad = ok & (o_g <= alpha_max);
      const V v_alpha = ok_grad ? t_front * dot - load<V>(s.vtt + p) / one_minus : zero;
      const V v_power = o_g * v_alpha;
      acc_op += gauss * v_alpha;
      acc_ca += T(-0.5) * dx * dx * v_power;
      acc_cb += -dx * dy * v_power;
      acc_cc += (T(-0.5) * dy * dy) * v_power;
      // d = pixel - mean, so d(power)/d(mean) = -d(power)/d(d).
      acc_mx += (g.ca * dx + g.cb * dy) * v_power;
      acc_my += (g.cb * dx + g.cc * dy) * v_power;
    }
    if (!entry_hit) {
      std::fill(dst, dst + S, T(0));
      continue;
    }
    dst[kMx] = simd::hsum(acc_mx);
    dst[kMy] = simd::hsum(acc_my);
    dst[kCa] = simd::hsum(acc_ca);
    dst[kCb] = simd::hsum(acc_cb);
    dst[kCc] = simd::hsum(acc_cc);
    dst[kOp] = simd::hsum(acc_op);
    acc_mx = acc_my = acc_ca = acc_cb = acc_cc = acc_op = zero;
    for (int c = 0; c < C; ++c) {
      T* af = acc_f + c * simd::kLanes;
      dst[kFeat + c] = simd::hsum(load<V>(af));
      std::fill(af, af + simd::kLanes, T(0));
    }
  }
}


template <typename T>
BackwardTileFn<T> pick(int channels) {
  switch (channels) {
    case 1:
      return &backward_tile<T, 1>;
    case 3:
      return &backward_tile<T, 3>;
    default:
      return &backward_tile<T, 0>;
  }
}
