// The per-tile kernel of the forward blend, written once and compiled once per instruction set:
// included (no include guard) inside a namespace of blend_fwd_cpu.cpp between
// COBGS_BEGIN_ISA_* / COBGS_END_ISA with COBGS_ISA_LEVEL set (see csrc/common/simd_cpu.h).
// NC > 0 fixes the channel count at compile time (RGB: 3, one mask label: 1), so the
// per-channel loops unroll; NC = 0 reads it from the arguments.
#include "../common/simd_isa_cpu.h"
#include "blend_block_cpu.h"

template <typename T, int NC>
void forward_tile(const FwdArgs<T>& a, int64_t tile, FwdScratch<T>& s) {
  using V = typename simd::Lanes<T>::V;
  using M = typename simd::Lanes<T>::M;
  using simd::VI;
  using simd::load;
  using simd::store;
  const V alpha_min = simd::splat<V>(T(math::kAlphaMin));
  const V alpha_max = simd::splat<V>(T(math::kAlphaMax));
  const V t_min = simd::splat<V>(T(math::kTransmittanceMin));
  const V zero = simd::splat<V>(T(0)), one = simd::splat<V>(T(1));
  const int C = NC > 0 ? NC : a.C, K = a.K;
  const bool lane_labels = a.labels != nullptr && K <= kLaneLabels;
  const int x0 = int(tile % a.tiles_x) * kTileSize, y0 = int(tile / a.tiles_x) * kTileSize;
  const int x1 = std::min(x0 + kTileSize, a.width), y1 = std::min(y0 + kTileSize, a.height);
  std::fill(s.Tp, s.Tp + kTilePixels, T(1));
  std::fill(s.last, s.last + kTilePixels, 0);
  std::fill(s.colour.begin(), s.colour.end(), T(0));
  // Pixels outside the image (edge tiles) start "done" so they never count as active.
  int active = 0;
  uint32_t live[kTileSize] = {0};  // per tile row: bit c set while pixel c is not done
  for (int p = 0; p < kTilePixels; ++p) {
    const bool inside = x0 + p % kTileSize < x1 && y0 + p / kTileSize < y1;
    s.done[p] = inside ? 0 : -1;
    active += inside;
    live[p / kTileSize] |= uint32_t(inside) << (p % kTileSize);
  }
  if (a.labels) {
    std::fill(s.tile_labels, s.tile_labels + kTilePixels, -1);
    for (int py = y0; py < y1; ++py)
      for (int px = x0; px < x1; ++px)
        s.tile_labels[(py - y0) * kTileSize + (px - x0)] = a.labels[int64_t(py) * a.width + px];
  }
  // Pixel-centre x of the tile's two column blocks (the same expression as the reference).
  V px_centre[2];
  for (int b = 0; b < 2; ++b)
    for (int k = 0; k < simd::kLanes; ++k)
      px_centre[b][k] = T(x0 + b * simd::kLanes + k) + T(0.5);
  // Label statistics of the current entry, per lane; summed once per entry.
  VI lane_cnt[kLaneLabels];
  V lane_w[kLaneLabels];
  for (int l = 0; l < kLaneLabels; ++l) {
    lane_cnt[l] = VI{};
    lane_w[l] = zero;
  }

  COBGS_PROF_LOCAL(n_entries);
  COBGS_PROF_LOCAL(n_blocks);
  COBGS_PROF_LOCAL(n_blocks_exp);
  COBGS_PROF_LOCAL(n_blended);
  const int64_t lo = a.off[tile], hi = a.off[tile + 1];
  for (int64_t j = lo; j < hi && active > 0; ++j) {
    if (j + kPrefetchAhead < hi) {
      const int32_t ahead = a.ids[j + kPrefetchAhead];
      COBGS_PREFETCH(&a.prep[ahead]);
      COBGS_PREFETCH(a.feat + int64_t(ahead) * C);
    }
    const int32_t gi = a.ids[j];
    const GaussPrep<T> g = a.prep[gi];
    const int gx0 = std::max(x0, g.x0), gx1 = std::min(x1, g.x1);
    const int gy0 = std::max(y0, g.y0), gy1 = std::min(y1, g.y1);
    if (gx0 >= gx1 || gy0 >= gy1) continue;
    const T* f = a.feat + int64_t(gi) * C;
    const VI rank = simd::splat<VI>(static_cast<int32_t>(j - lo + 1));
    const uint32_t cols = ((uint32_t(1) << (gx1 - gx0)) - 1) << (gx0 - x0);
    // The row segment is processed as the whole 8-pixel blocks it touches; the extra
    // pixels lie outside the conservative box (the exact test rejects them) or outside
    // the image (done).
    const int b0 = (gx0 - x0) / simd::kLanes, b1 = (gx1 - 1 - x0) / simd::kLanes;
    COBGS_PROF_ADD(n_entries, 1);
    // Phase 1a: the exponent and the candidate mask (pixel live, power within the bound
    // below which α < 1/255 for sure) of every block of the box; only blocks with some
    // candidate are kept (compacted without a branch), so exp is never evaluated on a
    // block outside the ellipse. Blocks of one entry are distinct pixels, so reading the
    // state here before phase 2 updates it is exact.
    int nblk = 0;
    for (int py = gy0; py < gy1; ++py) {
      // Rows whose pixels in the box have all stopped cost nothing.
      const uint32_t row_live = live[py - y0] & cols;
      if (!row_live) continue;
      const T dy = (T(py) + T(0.5)) - g.my;
      const T cc_dy_dy = g.cc * dy * dy;
      for (int b = b0; b <= b1; ++b) {
        if (!((row_live >> (b * simd::kLanes)) & 0xFFu)) continue;
        const int p = (py - y0) * kTileSize + b * simd::kLanes;
        // The per-pixel rule of 3DGS (see reference.py), in the reference's order:
        // power = -0.5 (a dx² + c dy²) - b dx dy.
        const V power = block_power<T>(g, px_centre[b], dy, cc_dy_dy);
        const VI cand = simd::to_i32(simd::to_mask(~load<VI>(s.done + p), T(0)) &
                                     (power <= zero) & (power >= g.power_reject));
        store(s.blk_alpha + nblk * simd::kLanes, power);
        store(s.blk_cand + nblk * simd::kLanes, cand);
        s.blk_pix[nblk] = p;
        nblk += any(cand);
        COBGS_PROF_ADD(n_blocks, 1);
      }
    }
    COBGS_PROF_ADD(n_blocks_exp, nblk);
    // Phase 1b: α = min(0.99, o·exp(power)) of the kept blocks: independent iterations
    // without branches, so the out-of-order core overlaps their exp chains (one block
    // alone is latency-bound).
    for (int i = 0; i < nblk; ++i) {
      T* ab = s.blk_alpha + i * simd::kLanes;
      store(ab, min_with(alpha_max, g.o * gauss_exp(load<V>(ab))));
    }
    // Phase 2: blend the candidates, front to back per pixel.
    bool entry_hit = false;  // the label lane sums hold something to flush
    for (int i = 0; i < nblk; ++i) {
      const V alpha = load<V>(s.blk_alpha + i * simd::kLanes);
      const M cand = simd::to_mask(load<VI>(s.blk_cand + i * simd::kLanes), T(0)) &
                     (alpha >= alpha_min);
      if (!any(simd::to_i32(cand))) continue;
      const int p = s.blk_pix[i];
      const V t_old = load<V>(s.Tp + p);
      const V test_t = t_old * (one - alpha);
      const M low = test_t < t_min;  // not blended; the pixel stops
      const M blend = cand & ~low;
      const M stop = cand & low;
      if (any(stop)) {
        store(s.done + p, load<VI>(s.done + p) | simd::to_i32(stop));
        const uint32_t sb = bits(stop);
        active -= __builtin_popcount(sb);
        live[p / kTileSize] &= ~(sb << (p % kTileSize));
      }
      if (!any(simd::to_i32(blend))) continue;
      COBGS_PROF_ADD(n_blended, __builtin_popcount(bits(simd::to_i32(blend))));
      store(s.Tp + p, blend ? test_t : t_old);
      const V w = blend ? alpha * t_old : zero;  // α·T of the blended pixels
      for (int c = 0; c < C; ++c) {
        T* col = s.colour.data() + size_t(c) * kTilePixels + p;
        const V cv = load<V>(col);
        store(col, blend ? cv + f[c] * w : cv);
      }
      const VI blend32 = simd::to_i32(blend);
      store(s.last + p, blend32 ? rank : load<VI>(s.last + p));
      if (lane_labels) {
        entry_hit = true;
        const VI lab = load<VI>(s.tile_labels + p);
        for (int l = 0; l < K; ++l) {
          const VI hit = blend32 & (lab == l);
          lane_cnt[l] -= hit;  // -(-1) per hit
          lane_w[l] += simd::to_mask(hit, T(0)) ? w : zero;
        }
      } else if (a.labels) {
        const int32_t* lab = s.tile_labels + p;
        int32_t* cnt = a.slot_counts + a.slot[j] * K;
        T* wts = a.slot_weights + a.slot[j] * K;
        for (uint32_t m = bits(blend32); m; m &= m - 1) {
          const int k = __builtin_ctz(m);
          if (lab[k] < 0) continue;
          cnt[lab[k]] += 1;
          wts[lab[k]] += w[k];
        }
      }
    }
    if (entry_hit) {
      int32_t* cnt = a.slot_counts + a.slot[j] * K;
      T* wts = a.slot_weights + a.slot[j] * K;
      for (int l = 0; l < K; ++l) {
        cnt[l] = simd::hsum(lane_cnt[l]);
        wts[l] = simd::hsum(lane_w[l]);
        lane_cnt[l] = VI{};
        lane_w[l] = zero;
      }
    }
  }

  COBGS_PROF_COUNT(kFwdEntries, n_entries);
  COBGS_PROF_COUNT(kFwdBlocks, n_blocks);
  COBGS_PROF_COUNT(kFwdBlocksExp, n_blocks_exp);
  COBGS_PROF_COUNT(kFwdBlended, n_blended);
  for (int py = y0; py < y1; ++py)
    for (int px = x0; px < x1; ++px) {
      const int p = (py - y0) * kTileSize + (px - x0);
      const int64_t pix = int64_t(py) * a.width + px;
      for (int c = 0; c < C; ++c)
        a.img[pix * C + c] = s.colour[size_t(c) * kTilePixels + p] + s.Tp[p] * a.bg[c];
      a.trans[pix] = s.Tp[p];
      a.n_contrib[pix] = s.last[p];
    }
}


template <typename T>
ForwardTileFn<T> pick(int channels) {
  switch (channels) {
    case 1:
      return &forward_tile<T, 1>;
    case 3:
      return &forward_tile<T, 3>;
    default:
      return &forward_tile<T, 0>;
  }
}
