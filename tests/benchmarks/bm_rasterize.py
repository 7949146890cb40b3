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


class Clock:
    """Wall time and process CPU time (all threads, user + system) of a block."""

    def __enter__(self):
        self.wall0, self.cpu0 = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc):
        self.wall = time.perf_counter() - self.wall0
        self.cpu = time.process_time() - self.cpu0


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
    from cobgs import _ops

    _, flat_ids = _ops.bin_tiles(out.means2d, out.radii, out.depths, W, H)
    contributions = int(out.label_counts.sum())
    print(f"scene: N = {args.n}, {W}x{H}, seed {args.seed}, threads {args.threads}, "
          f"OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY')}, torch {torch.__version__}")
    print(f"  visible {int(vis.sum())}, mean radius {out.radii[vis].float().mean():.2f} px, "
          f"tile-list entries {flat_ids.numel()}")
    print(f"  candidate pairs per pixel {flat_ids.numel() * 256 / (W * H):.1f}, blended "
          f"contributions per pixel {contributions / (W * H):.1f}, mean alpha "
          f"{out.alpha.mean():.3f}")

    load0 = os.getloadavg()[0]
    nat_f, nat_b, nat_fl, nat_fn = [], [], [], []
    for _ in range(args.reps):
        f, b, _ = run_once(tensors, "native", gi, ga)
        nat_f.append(f)
        nat_b.append(b)
        # Label overhead: forward-only pairs, interleaved so drift hits both equally.
        f0, _, _ = run_once(tensors, "native", gi, ga, backward=False)
        f1, _, _ = run_once(tensors, "native", gi, ga, labels=labels, backward=False)
        nat_fn.append(f0)
        nat_fl.append(f1)
    nf, nb = median_ms(nat_f), median_ms(nat_b)
    print(f"native    forward {nf:8.1f} ms   backward {nb:8.1f} ms   total {nf + nb:8.1f} ms"
          f"   (median of {args.reps}, wall)")
    # CPU time summed over threads: on a machine shared with other jobs the wall time
    # above includes waiting for a core; CPU / threads is what an idle machine would show.
    cf, cb = median_ms(nat_f, "cpu"), median_ms(nat_b, "cpu")
    print(f"native    CPU time  forward {cf:.1f} ms   backward {cb:.1f} ms   total "
          f"{cf + cb:.1f} ms (all threads; load average {load0:.1f} -> "
          f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs)")
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
