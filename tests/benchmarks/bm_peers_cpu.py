"""Our CPU rasterizer beside the CPU paths other splatting projects offer (issue 26, part 1).

Run in a benchmark-only environment that holds the peers next to this checkout (never
project dependencies)::

    python3 -m venv /tmp/peervenv && /tmp/peervenv/bin/pip install torch==2.13.0 gsplat \\
        plyfile opencv-python-headless scikit-image
    PYTHONPATH=. /tmp/peervenv/bin/python tests/benchmarks/bm_peers_cpu.py [--sizes 504x378,1008x756]
        [--counts 100000,1000000] [--reps 5] [--peer-reps 1] [--out results.json]

Peers:

* **gsplat's PyTorch path** (``gsplat/cuda/_torch_impl.py``, the reference its tests compare
  the CUDA kernels with): ``_fully_fused_projection`` (eps2d 0.3: the same 0.3 px² low-pass)
  → ``_isect_tiles`` / ``_isect_offset_encode`` (16 px tiles) → ``_rasterize_to_pixels``
  (front to back, α clamped at 0.99, skipped below 1/255, stop at T < 1e-4 — the rules our
  kernels follow); 3-σ radius as gsplat computes it; gradients through autograd. Its
  ``_rasterize_to_pixels`` (gsplat 1.5.3) finds the (Gaussian, pixel) pairs with a CUDA
  kernel (``rasterize_to_indices_in_range`` from ``_wrapper``), so the whole render cannot run
  without CUDA: the script records that, and times the part that is PyTorch — projection and
  sorted tile intersection, forward — beside ours (``cobgs.render.ops.project`` + ``bin_tiles``).
* **taichi-splatting** on Taichi's CPU backend: every release on PyPI (0.7.0–0.13.0) builds a
  CUDA library (radix sort, prefix sum) when imported and depends on ``taichi-nightly``,
  which is not on PyPI; it cannot run on a machine without CUDA. The script says so and
  records it instead of a time.

The scene (seeded): N Gaussians in front of a W x H pinhole camera (f = 0.833 W px, principal
point at the centre), depths uniform in [2, 8], x/y over 1.1x the frustum, random rotations,
log-normal scales (median 0.01 x 504 / W: the same footprint in pixels at every size),
opacities in [0.05, 0.95], RGB features, grey background. Forward + backward = the render
call with inputs requiring grad, then ``backward()`` of a fixed random linear loss on the
image; one training step = forward + backward + an Adam step on the five leaves. Times are
medians of wall time with 2 threads after one untimed warm-up call; ratios are peer / ours
measured in the same process.
A peer that runs out of time (``--peer-timeout-s``, default 600 s per call) or memory is
recorded as not run, with the reason.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "2")

import argparse  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import torch  # noqa: E402

TILE = 16


def make_scene(n: int, width: int, height: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    fx = fy = 420.0 * width / 504.0
    z = 2.0 + 6.0 * torch.rand(n, generator=g)
    half_w, half_h = 1.1 * (width / 2) / fx, 1.1 * (height / 2) / fy
    x = (2 * torch.rand(n, generator=g) - 1) * half_w * z
    y = (2 * torch.rand(n, generator=g) - 1) * half_h * z
    means = torch.stack([x, y, z], -1)
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1)
    scales = torch.exp(torch.log(torch.tensor(0.01 * 504.0 / width)) + 0.4 * torch.randn(n, 3, generator=g))
    opacities = 0.05 + 0.9 * torch.rand(n, generator=g)
    features = torch.rand(n, 3, generator=g)
    viewmat = torch.eye(4)
    K = torch.tensor([[fx, 0.0, width / 2], [0.0, fy, height / 2], [0.0, 0.0, 1.0]])
    grad_image = torch.randn(height, width, 3, generator=g)
    return (means, quats, scales, opacities, features, viewmat, K), grad_image


def ours(leaves, width, height):
    import cobgs

    means, quats, scales, opacities, features, viewmat, K = leaves
    bg = torch.full((3,), 0.5)
    return cobgs.rasterize(means, quats, scales, opacities, features, viewmat, K, width, height,
                           background=bg).image


def _gsplat_project_and_bin(tensors, width, height):
    """gsplat's PyTorch projection (eps2d 0.3) and sorted 16 px tile intersection:
    (means2d, conics, tile offsets, flat ids)."""
    from gsplat.cuda import _torch_impl as g

    means, quats, scales, opacities, features, viewmat, K = tensors
    covars, _ = g._quat_scale_to_covar_preci(quats, scales, compute_covar=True, compute_preci=False,
                                             triu=False)
    radii, means2d, depths, conics, _ = g._fully_fused_projection(
        means, covars, viewmat[None], K[None], width, height, eps2d=0.3)
    tw, th = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    _, isect_ids, flatten_ids = g._isect_tiles(means2d, radii, depths, TILE, tw, th)
    return means2d, conics, g._isect_offset_encode(isect_ids, 1, tw, th), flatten_ids


def gsplat_torch(leaves, width, height):
    from gsplat.cuda import _torch_impl as g

    features, opacities = leaves[4], leaves[3]
    means2d, conics, offsets, flatten_ids = _gsplat_project_and_bin(leaves, width, height)
    image, alpha = g._rasterize_to_pixels(means2d, conics, features[None], opacities[None], width, height, TILE,
                                          offsets, flatten_ids, backgrounds=torch.full((1, 3), 0.5))
    return image[0]


def ours_binning(tensors, width, height):
    from cobgs.render import ops

    means, quats, scales, opacities, features, viewmat, K = tensors
    means2d, conics, depths, radii = ops.project(means, quats, scales, viewmat, K, width, height)
    return ops.bin_tiles(means2d, radii, depths, width, height)


def gsplat_binning(tensors, width, height):
    _, _, offsets, flatten_ids = _gsplat_project_and_bin(tensors, width, height)
    return offsets, flatten_ids


def timed_fwd(fn, tensors, width, height, reps: int):
    times, out = [], None
    with torch.no_grad():
        fn(tensors, width, height)  # warm-up (first-call allocations, lazy imports)
        for _ in range(reps):
            t0 = time.perf_counter()
            out = fn(tensors, width, height)
            times.append(1e3 * (time.perf_counter() - t0))
    return statistics.median(times), out


def timed(fn, tensors, grad_image, width, height, reps: int, step: bool):
    """Median wall ms of forward + backward (and an Adam step with ``step``)."""
    times = []
    for rep in range(reps + 1):  # the first is a warm-up, not timed
        leaves = [t.clone().requires_grad_(i < 5) for i, t in enumerate(tensors)]
        opt = torch.optim.Adam(leaves[:5], lr=1e-3) if step else None
        t0 = time.perf_counter()
        img = fn(leaves, width, height)
        (img * grad_image).sum().backward()
        if opt is not None:
            opt.step()
        if rep:
            times.append(1e3 * (time.perf_counter() - t0))
    return statistics.median(times), img.detach()


def taichi_splatting_status() -> str:
    try:
        import taichi_splatting  # noqa: F401
    except Exception as exc:  # its import compiles CUDA sources: OSError / RuntimeError without CUDA
        return f"cannot run on this machine: importing taichi_splatting raised {type(exc).__name__}: {exc}"[:400]
    return "importable (a CPU run is not wired in: every release needs its CUDA library)"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", default="504x378,1008x756")
    ap.add_argument("--counts", default="100000,1000000")
    ap.add_argument("--reps", type=int, default=5, help="repetitions of ours (median)")
    ap.add_argument("--peer-reps", type=int, default=1, help="repetitions of each peer (median)")
    ap.add_argument("--peer-max-n", type=int, default=10**9, help="skip peers above this count")
    ap.add_argument("--out", default=None, help="write the rows as JSON here")
    args = ap.parse_args(argv)
    torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))
    try:
        import gsplat
        gs_version = gsplat.__version__
    except Exception as exc:  # pragma: no cover - the peer environment decides
        gs_version = f"not importable: {exc}"
    ts = taichi_splatting_status()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads; gsplat {gs_version}; "
          f"taichi-splatting: {ts}", flush=True)
    rows = []
    for size in args.sizes.split(","):
        width, height = (int(v) for v in size.split("x"))
        for n in (int(c) for c in args.counts.split(",")):
            tensors, grad_image = make_scene(n, width, height)
            row = {"width": width, "height": height, "n": n}
            row["ours_fwd_bwd_ms"], img_ours = timed(ours, tensors, grad_image, width, height, args.reps, False)
            row["ours_step_ms"], _ = timed(ours, tensors, grad_image, width, height, args.reps, True)
            line = (f"{width}x{height}, {n} Gaussians: ours fwd+bwd {row['ours_fwd_bwd_ms']:.1f} ms, "
                    f"step {row['ours_step_ms']:.1f} ms")
            row["ours_binning_ms"], ob = timed_fwd(ours_binning, tensors, width, height, args.reps)
            line += f"; projection + binning {row['ours_binning_ms']:.1f} ms ({int(ob[1].numel())} pairs)"
            if n <= args.peer_max_n:
                try:
                    ms, gb = timed_fwd(gsplat_binning, tensors, width, height, args.peer_reps)
                    row["gsplat_binning_ms"] = ms
                    row["gsplat_binning_ratio"] = ms / row["ours_binning_ms"]
                    line += (f"; gsplat torch projection + intersection {ms:.0f} ms = "
                             f"{row['gsplat_binning_ratio']:.1f}x ours ({int(gb[1].numel())} pairs)")
                except (RuntimeError, MemoryError) as exc:
                    row["gsplat_binning"] = f"not run: {type(exc).__name__}: {str(exc)[:200]}"
            if n > args.peer_max_n:
                row["gsplat_torch"] = f"not run: above --peer-max-n {args.peer_max_n}"
            else:
                try:
                    ms, img = timed(gsplat_torch, tensors, grad_image, width, height, args.peer_reps, False)
                    row["gsplat_torch_fwd_bwd_ms"] = ms
                    row["gsplat_torch_ratio"] = ms / row["ours_fwd_bwd_ms"]
                    row["image_max_abs_diff"] = float((img - img_ours).abs().max())
                    line += (f"; gsplat torch fwd+bwd {ms:.0f} ms = {row['gsplat_torch_ratio']:.1f}x ours "
                             f"(image |diff| max {row['image_max_abs_diff']:.2g})")
                except (RuntimeError, MemoryError, ImportError, OSError, TypeError) as exc:
                    # gsplat 1.5.3: its PyTorch rasterizer calls a CUDA kernel (module docstring)
                    row["gsplat_torch"] = f"not run: {type(exc).__name__}: {str(exc)[:200]}"
                    line += f"; gsplat torch fwd+bwd: {row['gsplat_torch']}"
            row["taichi_splatting"] = ts
            print(line, flush=True)
            rows.append(row)
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"torch": torch.__version__, "gsplat": gs_version, "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
