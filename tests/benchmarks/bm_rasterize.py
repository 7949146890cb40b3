"""Benchmark of cobgs.rasterize: native C++ ops vs the pure-PyTorch reference, same run.

Run (not collected by pytest)::

    .venv/bin/python tests/benchmarks/bm_rasterize.py            # defaults below
    .venv/bin/python tests/benchmarks/bm_rasterize.py --reps 21 --ref-reps 3

Scene (seeded, ``--seed 0``): 100,000 Gaussians in front of a 504x378 pinhole camera
(fx = fy = 420 px, principal point at the centre; identity pose, looking down +z).
Depths are uniform in [2, 8]; x/y are uniform over 1.1x the view frustum at that depth
(so a few percent fall outside and are culled); rotations are random unit quaternions;
the three scales of each Gaussian are log-normal, median 0.01, σ_log 0.4, so the
projected standard deviation fx·s/z is about 1 px on average and the 3-sigma radius
(with the 0.3 px² low-pass) a few px; opacities are uniform in [0.05, 0.95]; features
are RGB in [0, 1]; background grey. The script prints the mean radius, the tile-list
length, the candidate pairs per pixel (tile-list entries x 256 / pixels: the pairs the
blending loop has to consider), and the blended contributions per pixel.

Timings use 2 threads (torch.set_num_threads and OMP_NUM_THREADS) and report medians
of wall time; the native rows also report process CPU time (all threads), since on a
machine shared with other jobs the wall time includes waiting for a core (the load
average is printed).
Forward = the ``cobgs.rasterize`` call with inputs requiring grad (projection, binning,
blending, autograd bookkeeping); backward = ``loss.backward()`` for a fixed random
linear loss on image and alpha. The label-statistics overhead is the native forward with
a binary ``pixel_labels`` image relative to the same forward without.

Floor model (printed next to the achieved times). Pairs *evaluated*: (Gaussian, pixel)
pairs whose pixel centre lies in the Gaussian's α >= 1/255 bounding box (from its conic
and opacity) inside a tile whose list holds it — what any exact kernel has to test. Pairs
*contributing*: pairs actually blended (from the label counts). FLOPs per pair, counted
on the formulas of csrc/common/gs_math.h (every add, mul, compare, min/max, division):

* forward, per evaluated pair 37 (power 8, exp 24, α 2, tests 3); per contributing pair
  4 + 2C (transmittance, weight, colour);
* backward, per evaluated pair 37 (the forward's decision recomputed); per contributing
  pair 15 + 9C (T in front, dL/df, R update, dL/dα, conic/mean/opacity sums);
* projection ~170 per visible Gaussian forward, ~420 backward (estimates).

Peak: float32 GEMM (torch.mm 384x384, best of 30) on one thread, times the thread count:
the machine's FMA peak, an upper bound for kernels that, like these, use separate
multiplies and adds (-ffp-contract=off). The floor time is FLOPs / peak; the ratio
achieved / floor says how far the kernels are from compute-bound. CPU time is compared
with FLOPs / peak-per-thread.

Targets (issue 10): forward + backward <= 60 ms wall (2 threads, 504x378, 100k).
The CPU fast path (issue 45: fused multiply-adds, ``cobgs.render.ops.cpu_fast_path``) is
timed in the same loop, one run of each path per repetition, and printed as ratios.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "2")
# libgomp (used by torch and by the extension) spin-waits between parallel regions by
# default. On a machine shared with other jobs (more runnable threads than cores) the
# spinning thread takes the core its partner needs, which more than doubled wall times
# here. Passive waiting is the default of this benchmark; export OMP_WAIT_POLICY=active
# (or any value) before running to measure another policy. It applies to the native and
# the reference runs alike.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch  # noqa: E402

import cobgs  # noqa: E402
from _bench_util import Clock  # noqa: E402  (the script's folder is on sys.path when run as a script)

W, H = 504, 378


def make_scene(n: int, seed: int, dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    fx = fy = 420.0
    z = 2.0 + 6.0 * torch.rand(n, generator=g)
    half_w, half_h = 1.1 * (W / 2) / fx, 1.1 * (H / 2) / fy
    x = (2 * torch.rand(n, generator=g) - 1) * half_w * z
    y = (2 * torch.rand(n, generator=g) - 1) * half_h * z
    means = torch.stack([x, y, z], -1)
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1)
    scales = torch.exp(torch.log(torch.tensor(0.01)) + 0.4 * torch.randn(n, 3, generator=g))
    opacities = 0.05 + 0.9 * torch.rand(n, generator=g)
    features = torch.rand(n, 3, generator=g)
    viewmat = torch.eye(4)
    K = torch.tensor([[fx, 0.0, W / 2], [0.0, fy, H / 2], [0.0, 0.0, 1.0]])
    # A binary "object mask": a disc covering ~20% of the image.
    yy, xx = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    labels = (((xx - W / 2) ** 2 + (yy - H / 2) ** 2) < (0.25 * W) ** 2).to(torch.int32)
    tensors = [t.to(dtype) for t in (means, quats, scales, opacities, features, viewmat, K)]
    grad_image = torch.randn(H, W, 3, generator=g).to(dtype)
    grad_alpha = torch.randn(H, W, generator=g).to(dtype)
    return tensors, labels, grad_image, grad_alpha




def run_once(tensors, backend, grad_image, grad_alpha, labels=None, backward=True):
    """Returns (forward Clock, backward Clock or None, output)."""
    leaves = [t.clone().requires_grad_(i < 5) for i, t in enumerate(tensors)]
    bg = torch.full((3,), 0.5, dtype=tensors[0].dtype)
    with Clock() as fwd:
        out = cobgs.rasterize(*leaves, W, H, background=bg, pixel_labels=labels,
                              backend=backend)
    if not backward:
        return fwd, None, out
    loss = (out.image * grad_image).sum() + (out.alpha * grad_alpha).sum()
    with Clock() as bwd:
        loss.backward()
    return fwd, bwd, out


def median_ms(clocks, attr="wall"):
    return 1000 * statistics.median(getattr(c, attr) for c in clocks)


FLOP_FWD_EVAL, FLOP_BWD_EVAL = 37, 37
FLOP_PROJ_FWD, FLOP_PROJ_BWD = 170, 420


def flop_fwd_contrib(c: int) -> int:
    return 4 + 2 * c


def flop_bwd_contrib(c: int) -> int:
    return 15 + 9 * c


def count_evaluated(m2, co, opac, tile_offsets, ids, width, height) -> int:
    """Pairs evaluated (see the module docstring) of one render's projection and tiles."""
    ts = 16
    tiles_x = (width + ts - 1) // ts
    counts = tile_offsets[1:] - tile_offsets[:-1]
    tile = torch.repeat_interleave(torch.arange(counts.numel()), counts)
    g = ids.long()
    a, b, c = co[g, 0], co[g, 1], co[g, 2]
    o = opac.double()[g]
    det = a * c - b * b
    L = torch.log(255.0 * o)
    two_l = 2.0 * L
    ok = (o >= 1 / 255) & (det > 0) & (a > 0) & (two_l > 0)
    hx = torch.sqrt((two_l * c / det).clamp_min(0))
    hy = torch.sqrt((two_l * a / det).clamp_min(0))
    mx, my = m2[g, 0], m2[g, 1]
    tx0 = (tile % tiles_x) * ts
    ty0 = (tile // tiles_x) * ts
    x0 = torch.maximum(torch.ceil(mx - 0.5 - hx), tx0.double())
    x1 = torch.minimum(torch.floor(mx - 0.5 + hx) + 1, (tx0 + ts).clamp(max=width).double())
    y0 = torch.maximum(torch.ceil(my - 0.5 - hy), ty0.double())
    y1 = torch.minimum(torch.floor(my - 0.5 + hy) + 1, (ty0 + ts).clamp(max=height).double())
    area = (x1 - x0).clamp_min(0) * (y1 - y0).clamp_min(0)
    return int(torch.where(ok, area, torch.zeros_like(area)).sum())


def peak_gflops_per_thread() -> float:
    """float32 GEMM rate on one thread (best of 30), in GFLOP/s."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        a, b = torch.randn(384, 384), torch.randn(384, 384)
        for _ in range(5):
            a @ b
        best = float("inf")
        for _ in range(30):
            t = time.perf_counter()
            for _ in range(4):
                a @ b
            best = min(best, (time.perf_counter() - t) / 4)
    finally:
        torch.set_num_threads(before)
    return 2 * 384 ** 3 / best / 1e9


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=100_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--reps", type=int, default=15, help="native repetitions")
    ap.add_argument("--ref-reps", type=int, default=3, help="reference repetitions")
    ap.add_argument("--skip-reference", action="store_true")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    tensors, labels, gi, ga = make_scene(args.n, args.seed)

    # Warm-up (also builds/loads the extension) and scene statistics.
    _, _, out = run_once(tensors, "native", gi, ga, labels=torch.zeros(H, W, dtype=torch.int32))
    vis = out.radii > 0
    from cobgs.render import ops

    tile_offsets, flat_ids = ops.bin_tiles(out.means2d, out.radii, out.depths, W, H)
    contributions = int(out.label_counts.sum())
    evaluated = count_evaluated(out.means2d.detach().double(), out.conics.detach().double(),
                                tensors[3], tile_offsets, flat_ids, W, H)
    print(f"scene: N = {args.n}, {W}x{H}, seed {args.seed}, threads {args.threads}, "
          f"OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY')}, torch {torch.__version__}")
    _, tight_ids, _ = ops.bin_tiles_tight(out.means2d, out.radii, out.depths, out.conics,
                                           tensors[3].detach(), W, H)
    print(f"  visible {int(vis.sum())}, mean radius {out.radii[vis].float().mean():.2f} px, "
          f"tile-list entries {flat_ids.numel()} (3-sigma boxes; the tight lists rasterize "
          f"uses: {tight_ids.numel()}, {100 * tight_ids.numel() / max(1, flat_ids.numel()):.0f}%)")
    print(f"  candidate pairs per pixel {flat_ids.numel() * 256 / (W * H):.1f}, blended "
          f"contributions per pixel {contributions / (W * H):.1f}, mean alpha "
          f"{out.alpha.mean():.3f}")
    print(f"  pairs evaluated (α >= 1/255 box within the tile) {evaluated / 1e6:.2f} M "
          f"({evaluated / (W * H):.1f} per pixel), pairs contributing {contributions / 1e6:.2f} M")

    load0 = os.getloadavg()[0]
    nat_f, nat_b, nat_fl, nat_fn, fast_f, fast_b = [], [], [], [], [], []
    for _ in range(args.reps):
        f, b, _ = run_once(tensors, "native", gi, ga)
        nat_f.append(f)
        nat_b.append(b)
        # The CPU fast path (fused multiply-adds, issue 45), interleaved with the exact one.
        with ops.cpu_fast_path(True):
            f, b, _ = run_once(tensors, "native", gi, ga)
        fast_f.append(f)
        fast_b.append(b)
        # Label overhead: forward-only pairs, interleaved so drift hits both equally.
        f0, _, _ = run_once(tensors, "native", gi, ga, backward=False)
        f1, _, _ = run_once(tensors, "native", gi, ga, labels=labels, backward=False)
        nat_fn.append(f0)
        nat_fl.append(f1)
    nf, nb = median_ms(nat_f), median_ms(nat_b)
    print(f"native    forward {nf:8.1f} ms   backward {nb:8.1f} ms   total {nf + nb:8.1f} ms"
          f"   (median of {args.reps}, wall)")
    ff_, fb_ = median_ms(fast_f), median_ms(fast_b)
    with ops.cpu_fast_path(True):
        _, _, out_fast = run_once(tensors, "native", gi, ga, backward=False)
    _, _, out_exact = run_once(tensors, "native", gi, ga, backward=False)
    diff = float((out_fast.image - out_exact.image).abs().max())
    print(f"fast path forward {ff_:8.1f} ms   backward {fb_:8.1f} ms   total {ff_ + fb_:8.1f} ms"
          f"   (median of {args.reps}, wall; exact / fast: forward {nf / ff_:.2f}x, backward "
          f"{nb / fb_:.2f}x, total {(nf + nb) / (ff_ + fb_):.2f}x; CPU time exact / fast "
          f"{(median_ms(nat_f, 'cpu') + median_ms(nat_b, 'cpu')) / (median_ms(fast_f, 'cpu') + median_ms(fast_b, 'cpu')):.2f}x;"
          f" image max |fast - exact| {diff:.2e})")
    # CPU time summed over threads: on a machine shared with other jobs the wall time
    # above includes waiting for a core; CPU / threads is what an idle machine would show.
    cf, cb = median_ms(nat_f, "cpu"), median_ms(nat_b, "cpu")
    print(f"native    CPU time  forward {cf:.1f} ms   backward {cb:.1f} ms   total "
          f"{cf + cb:.1f} ms (all threads; load average {load0:.1f} -> "
          f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs)")
    # Floor model (module docstring), measured under the same load.
    C = tensors[4].shape[1]
    n_vis = int(vis.sum())
    flop_f = (evaluated * FLOP_FWD_EVAL + contributions * flop_fwd_contrib(C)
              + n_vis * FLOP_PROJ_FWD)
    flop_b = (evaluated * FLOP_BWD_EVAL + contributions * flop_bwd_contrib(C)
              + n_vis * FLOP_PROJ_BWD)
    peak1 = peak_gflops_per_thread()
    peak = peak1 * args.threads
    ff, fb = flop_f / peak / 1e6, flop_b / peak / 1e6  # ms at the machine peak
    print(f"floor model: {FLOP_FWD_EVAL} + {FLOP_BWD_EVAL} FLOP per evaluated pair, "
          f"{flop_fwd_contrib(C)} + {flop_bwd_contrib(C)} per contributing pair (fwd + bwd), "
          f"{flop_f / 1e6:.0f} + {flop_b / 1e6:.0f} MFLOP")
    print(f"  peak (float32 GEMM, in-run) {peak1:.1f} GFLOP/s per thread x {args.threads} = "
          f"{peak:.1f} GFLOP/s -> floor forward {ff:.2f} ms, backward {fb:.2f} ms, total "
          f"{ff + fb:.2f} ms")
    print(f"  achieved / floor: wall {(nf + nb) / (ff + fb):.1f}x (forward {nf / ff:.1f}x, "
          f"backward {nb / fb:.1f}x); CPU time {(cf + cb) / (args.threads * (ff + fb)):.1f}x "
          f"(CPU {cf + cb:.1f} ms vs {args.threads * (ff + fb):.2f} ms of one thread at peak)")
    print(f"  target (issue 10): forward + backward <= 60 ms wall: "
          f"{'met' if nf + nb <= 60 else 'not met'} in this run ({nf + nb:.1f} ms, load "
          f"average {os.getloadavg()[0]:.1f}); CPU time / threads {(cf + cb) / args.threads:.1f} ms")
    plain, with_labels = median_ms(nat_fn), median_ms(nat_fl)
    print(f"label statistics: forward {plain:.1f} ms -> {with_labels:.1f} ms with labels "
          f"(+{100 * (with_labels / plain - 1):.1f}% wall; CPU time "
          f"+{100 * (median_ms(nat_fl, 'cpu') / median_ms(nat_fn, 'cpu') - 1):.1f}%)")
    if args.skip_reference:
        return 0
    ref_f, ref_b = [], []
    for _ in range(args.ref_reps):
        f, b, _ = run_once(tensors, "reference", gi, ga)
        ref_f.append(f)
        ref_b.append(b)
    rf, rb = median_ms(ref_f), median_ms(ref_b)
    print(f"reference forward {rf:8.1f} ms   backward {rb:8.1f} ms   total {rf + rb:8.1f} ms"
          f"   (median of {args.ref_reps}, wall)")
    print(f"speed-up (reference / native, wall): forward {rf / nf:.1f}x, backward "
          f"{rb / nb:.1f}x, forward+backward {(rf + rb) / (nf + nb):.1f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
