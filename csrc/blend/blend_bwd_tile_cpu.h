// The per-tile kernel of the backward blend, written once and compiled once per instruction set:
// included (no include guard) inside a namespace of blend_bwd_cpu.cpp between
// COBGS_BEGIN_ISA_* / COBGS_END_ISA with COBGS_ISA_LEVEL set (see csrc/common/simd_cpu.h).
// NC > 0 fixes the channel count at compile time (RGB: 3, one mask label: 1), so the
// per-channel loops unroll; NC = 0 reads it from the arguments.
#include "../common/simd_isa_cpu.h"
#include "blend_block_cpu.h"

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
  // Per-lane gradient sums of the current entry (all zero between entries): Σ dy²·v_power,
  // Σ G·v_alpha, per block column Σ v_power and Σ dy·v_power, and per channel Σ α T dL/dC
  // (in registers when the channel count is fixed, else in s.acc_f).
  V acc_r = zero, acc_op = zero;
  V acc_p0 = zero, acc_p1 = zero, acc_q0 = zero, acc_q1 = zero;
  constexpr int kRegF = NC > 0 ? NC : 1;
  V acc_fr[kRegF];
  for (int c = 0; c < kRegF; ++c) acc_fr[c] = zero;
  T* acc_f = s.acc_f.data();
  auto acc_f_get = [&](int c) -> V {
    if constexpr (NC > 0) {
      return acc_fr[c];
    } else {
      return load<V>(acc_f + c * simd::kLanes);
    }
  };
  // Entries behind every pixel's last contributor have nothing to do (and no slot:
  // group_live_entries gave slots to the first max_last entries only).

  COBGS_PROF_LOCAL(n_blocks);
  COBGS_PROF_LOCAL(n_blocks_exp);
  COBGS_PROF_LOCAL(n_blended);
  for (int64_t rank = max_last - 1; rank >= 0; --rank) {
    const int64_t j = lo + rank;
    if (rank >= kPrefetchAhead) {
      const int32_t ahead = a.ids[j - kPrefetchAhead];
      COBGS_PREFETCH(&a.prep[ahead]);
      COBGS_PREFETCH(a.feat + int64_t(ahead) * C);
      COBGS_PREFETCH_W(a.slot_grad + a.slot[j - kPrefetchAhead] * S);
    }
    const int64_t slot = a.slot[j];
    const int32_t gi = a.ids[j];
    const GaussPrep<T> g = a.prep[gi];
    const int gx0 = std::max(x0, g.x0), gx1 = std::min(x1, g.x1);
    const int gy0 = std::max(y0, g.y0), gy1 = std::min(y1, g.y1);
    if (gx0 >= gx1 || gy0 >= gy1) {
      a.slot_hit[slot] = 0;
      continue;
    }
    const T* f = a.feat + int64_t(gi) * C;
    const int b0 = (gx0 - x0) / simd::kLanes, b1 = (gx1 - 1 - x0) / simd::kLanes;
    const int32_t rank32 = static_cast<int32_t>(rank);
    const VI rank_v = simd::splat<VI>(rank32);
    // Phase 1a: the exponent and the mask of pixels where the forward may have blended
    // this entry (in front of the pixel's last contributor, power within the bound) of
    // every block of the box; only blocks with some such pixel are kept (compacted
    // without a branch), so exp is never evaluated outside the ellipse.
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
        const V power = block_power<T>(g, px_centre[b], dy, cc_dy_dy);
        const VI ok = simd::to_i32(simd::to_mask(rank_v < load<VI>(s.last + p), T(0)) &
                                   (power <= zero) & (power >= g.power_reject));
        store(s.blk_gauss + nblk * simd::kLanes, power);
        store(s.blk_ok + nblk * simd::kLanes, ok);
        s.blk_pix[nblk] = p;
        nblk += any(ok);
        COBGS_PROF_ADD(n_blocks, 1);
      }
    }
    COBGS_PROF_ADD(n_blocks_exp, nblk);
    // Phase 1b: exp of the kept blocks (independent iterations without branches: the
    // out-of-order core overlaps their exp chains).
    for (int i = 0; i < nblk; ++i) {
      T* gb = s.blk_gauss + i * simd::kLanes;
      store(gb, gauss_exp(load<V>(gb)));
    }
    // Phase 2: gradients of the blended pixels.
    bool entry_hit = false;  // the accumulators hold something (all zero otherwise)
    for (int i = 0; i < nblk; ++i) {
      const V gauss = load<V>(s.blk_gauss + i * simd::kLanes);
      const V o_g = g.o * gauss;
      const V alpha = min_with(alpha_max, o_g);
      // The forward's decision, recomputed bit for bit.
      const M ok = simd::to_mask(load<VI>(s.blk_ok + i * simd::kLanes), T(0)) &
                   (alpha >= alpha_min);
      if (!any(simd::to_i32(ok))) continue;
      entry_hit = true;
      COBGS_PROF_ADD(n_blended, __builtin_popcount(bits(simd::to_i32(ok))));
      const int p = s.blk_pix[i];
      const T dy = (T(y0 + p / kTileSize) + T(0.5)) - g.my;
      const int col = (p % kTileSize) / simd::kLanes;  // block column
      const V one_minus = one - alpha;
      const V t_after = load<V>(s.Tp + p);
      const V inv_om = one / one_minus;  // one division for both quotients below
      const V t_front = t_after * inv_om;  // T in front of this Gaussian
      store(s.Tp + p, ok ? t_front : t_after);
      // Per channel: dL/df = α T dL/dC, Σ_c (f_c - R_c) dL/dC_c, then R ← α f + (1 - α) R.
      V dot = zero;
      for (int c = 0; c < C; ++c) {
        const T fc = f[c];
        T* r = s.rest.data() + size_t(c) * kTilePixels + p;
        const V v_ok = ok ? load<V>(s.vcol.data() + size_t(c) * kTilePixels + p) : zero;
        const V rv = load<V>(r);
        if constexpr (NC > 0) {
          acc_fr[c] += alpha * t_front * v_ok;
        } else {
          T* af = acc_f + c * simd::kLanes;
          store(af, load<V>(af) + alpha * t_front * v_ok);
        }
        dot += (fc - rv) * v_ok;
        store(r, ok ? alpha * fc + one_minus * rv : rv);
      }
      // dL/dα → opacity, conic and mean (no gradient where the 0.99 clamp is active);
      // a zero v_alpha makes every term below zero.
      const M ok_grad = ok & (o_g <= alpha_max);
      const V v_alpha = ok_grad ? t_front * dot - load<V>(s.vtt + p) * inv_om : zero;
      const V v_power = o_g * v_alpha;
      acc_op += gauss * v_alpha;
      // power = -0.5 (a dx² + c dy²) - b dx dy with dx fixed per lane of a block column
      // and dy fixed per row: per-lane sums of v_power and dy·v_power per column, and of
      // dy²·v_power, give every conic and mean gradient at the end of the entry.
      if (col == 0) {
        acc_p0 += v_power;
        acc_q0 += dy * v_power;
      } else {
        acc_p1 += v_power;
        acc_q1 += dy * v_power;
      }
      acc_r += (dy * dy) * v_power;
    }
    if (!entry_hit) {
      a.slot_hit[slot] = 0;
      continue;
    }
    T* dst = a.slot_grad + slot * S;
    a.slot_hit[slot] = 1;
    // The entry's sums: Σ dx v_power, Σ dy v_power, Σ dx² v_power, Σ dx dy v_power,
    // Σ dy² v_power, Σ G v_alpha and the first two channels' Σ α T dL/dC, lane sums
    // added in one batch (simd::hsum8, the same bits as one at a time).
    {
      const V dx0 = px_centre[0] - g.mx, dx1 = px_centre[1] - g.mx;
      const V p0 = acc_p0, p1 = acc_p1, q0 = acc_q0, q1 = acc_q1;
      const V parts[8] = {dx0 * p0 + dx1 * p1,
                          q0 + q1,
                          dx0 * dx0 * p0 + dx1 * dx1 * p1,
                          dx0 * q0 + dx1 * q1,
                          acc_r,
                          acc_op,
                          C > 0 ? acc_f_get(0) : zero,
                          C > 1 ? acc_f_get(1) : zero};
      T sums[8];
      simd::hsum8(parts, sums);
      const T s_dx = sums[0], s_dy = sums[1];
      dst[kCa] = T(-0.5) * sums[2];
      dst[kCb] = -sums[3];
      dst[kCc] = T(-0.5) * sums[4];
      // d = pixel - mean, so d(power)/d(mean) = -d(power)/d(d).
      dst[kMx] = g.ca * s_dx + g.cb * s_dy;
      dst[kMy] = g.cb * s_dx + g.cc * s_dy;
      dst[kOp] = sums[5];
      for (int c = 0; c < std::min(C, 2); ++c) dst[kFeat + c] = sums[6 + c];
    }
    acc_r = acc_op = acc_p0 = acc_p1 = acc_q0 = acc_q1 = zero;
    for (int c = 2; c < C; ++c) dst[kFeat + c] = simd::hsum(acc_f_get(c));
    if constexpr (NC > 0) {
      for (int c = 0; c < kRegF; ++c) acc_fr[c] = zero;
    } else {
      std::fill(acc_f, acc_f + size_t(C) * simd::kLanes, T(0));
    }
  }
  COBGS_PROF_COUNT(kBwdBlocks, n_blocks);
  COBGS_PROF_COUNT(kBwdBlocksExp, n_blocks_exp);
  COBGS_PROF_COUNT(kBwdBlended, n_blended);
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
