"""CUDA backend benchmarks (needs a CUDA device and an extension built with its kernels).

Usage::

    python tests/benchmarks/bm_cuda.py kernels [--sizes 100000,1000000] [--reps 20]
    python tests/benchmarks/bm_cuda.py fern --images ../shared/data/llff_fern/images_4 \\
        [--iterations 30000] [--out /tmp/bm_cuda]

``kernels``: forward + backward of one render at 1008x756 (4 feature channels) with N
Gaussians, ours (``cobgs.rasterize``: projection, tight binning, blending, and the
backward of all three through autograd) against gsplat's ``rasterization`` (PyPI package,
its defaults apart from the matched conventions: 0.3 px² low-pass, near plane 0.01, 16 px
tiles; both ``packed`` settings timed, the faster is the reference) on the same Gaussians
and camera, in one run on one GPU. Random Gaussians in the view frustum (depth 2..10,
footprints of ~1 to ~40 px, half of them faint). Times are medians over ``--reps``
CUDA-event-timed repetitions after warm-up; the image difference between the two
renderers is printed as a check that both did the same work.

``fern``: the NVOS-protocol scene cost on the GPU: SfM (pycolmap, CPU) on the 20 images
at 1008x756, full 3DGS training (default recipe, 30k iterations), then COB-GS refinement
(forward-facing defaults: 22·V iterations) of one object whose masks are rendered from
the trained scene (the Gaussians within a sphere around the scene's centre, visible
where they hold the pixel: per-view masks at the training resolution); wall time and
peak GPU memory of each, with the GPU's name. Writes ``fern.ply`` (for the parity tests:
``COBGS_TRAINED_PLY``) and ``bm_cuda_fern.json`` into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))


def gpu_name() -> str:
    p = torch.cuda.get_device_properties(0)
    return f"{p.name} ({p.multi_processor_count} SMs, {p.total_memory / 2**30:.0f} GiB)"


def frustum_scene(n: int, width: int, height: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    f = 0.8 * width
    z = 2.0 + 8.0 * torch.rand(n, generator=g)
    x = (torch.rand(n, generator=g) * 2 - 1) * 0.7 * z * width / (2 * f)
    y = (torch.rand(n, generator=g) * 2 - 1) * 0.7 * z * height / (2 * f)
    means = torch.stack([x, y, z], -1)
    # Footprints from ~1 to ~40 px: σ_px = f σ / z.
    sigma_px = torch.exp(torch.rand(n, 3, generator=g) * math.log(40.0)) / 3.0
    scales = sigma_px * z[:, None] / f
    quats = torch.randn(n, 4, generator=g)
    opacities = torch.where(torch.rand(n, generator=g) < 0.5, 0.02 + 0.1 * torch.rand(n, generator=g),
                            0.3 + 0.69 * torch.rand(n, generator=g))
    colors = torch.rand(n, 4, generator=g)
    viewmat = torch.eye(4)
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    dev = torch.device("cuda")
    return [t.to(dev) for t in (means, quats, scales, opacities, colors, viewmat, K)]


def time_cuda(fn, reps: int, warmup: int = 3) -> tuple[float, float]:
    """Median and minimum milliseconds of fn() over reps runs (CUDA events)."""
    for _ in range(warmup):
        fn()
    torch.cuda.synchronize()
    times = []
    for _ in range(reps):
        a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        a.record()
        fn()
        b.record()
        b.synchronize()
        times.append(a.elapsed_time(b))
    return statistics.median(times), min(times)


def profile_kernels(label: str, fn, reps: int = 5) -> None:
    """Per-kernel GPU time of fn (torch.profiler), averaged over reps calls."""
    from torch.profiler import ProfilerActivity, profile

    fn()
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        for _ in range(reps):
            fn()
        torch.cuda.synchronize()
    print(f"--- profile: {label} (per call, {reps} calls)")
    print(prof.key_averages().table(sort_by="self_cuda_time_total", row_limit=22,
                                    max_name_column_width=90))


def bench_kernels(args) -> None:
    import cobgs

    w, h = args.width, args.height
    print(f"GPU: {gpu_name()}; torch {torch.__version__}; {w}x{h}, 4 channels, "
          f"median of {args.reps} (min in brackets)")
    try:
        import gsplat
        from gsplat import rasterization
        print(f"gsplat {gsplat.__version__}")
    except Exception as exc:  # noqa: BLE001 - report why the peer is missing
        rasterization = None
        print(f"gsplat not available: {exc}")
    rows = []
    for n in (int(s) for s in args.sizes.split(",")):
        means, quats, scales, opac, colors, viewmat, K = frustum_scene(n, w, h)
        weight = torch.rand(h, w, 4, device="cuda", generator=torch.Generator("cuda").manual_seed(1))
        leaves = [t.clone().requires_grad_() for t in (means, quats, scales, opac, colors)]

        def ours():
            for t in leaves:
                t.grad = None
            out = cobgs.rasterize(*leaves, viewmat, K, w, h)
            (out.image * weight).sum().backward()
            return out

        def ours_fwd():
            with torch.no_grad():
                return cobgs.rasterize(*leaves, viewmat, K, w, h)

        torch.cuda.reset_peak_memory_stats()
        t_ours, t_ours_min = time_cuda(ours, args.reps)
        mem_ours = torch.cuda.max_memory_allocated()
        t_ours_fwd, _ = time_cuda(ours_fwd, args.reps)
        row = {"n": n, "ours_ms": t_ours, "ours_min_ms": t_ours_min, "ours_fwd_ms": t_ours_fwd,
               "ours_peak_mem": mem_ours}
        line = (f"N={n:>8}: ours fwd+bwd {t_ours:7.2f} ms [{t_ours_min:.2f}] "
                f"(fwd {t_ours_fwd:.2f}), peak {mem_ours / 2**20:.0f} MiB")
        if rasterization is not None:
            best = None
            for packed in (True, False):
                def peer(packed=packed):
                    for t in leaves:
                        t.grad = None
                    img, alpha, _ = rasterization(leaves[0], leaves[1], leaves[2], leaves[3],
                                                  leaves[4], viewmat[None], K[None], w, h,
                                                  near_plane=0.01, eps2d=0.3, packed=packed,
                                                  tile_size=16)
                    (img[0] * weight).sum().backward()
                    return img

                def peer_fwd(packed=packed):
                    with torch.no_grad():
                        return rasterization(leaves[0], leaves[1], leaves[2], leaves[3],
                                             leaves[4], viewmat[None], K[None], w, h,
                                             near_plane=0.01, eps2d=0.3, packed=packed,
                                             tile_size=16)[0]

                torch.cuda.reset_peak_memory_stats()
                t, t_min = time_cuda(peer, args.reps)
                mem = torch.cuda.max_memory_allocated()
                t_fwd, _ = time_cuda(peer_fwd, args.reps)
                row[f"gsplat_packed{int(packed)}_ms"] = t
                row[f"gsplat_packed{int(packed)}_fwd_ms"] = t_fwd
                line += (f"\n    gsplat packed={packed}: fwd+bwd {t:7.2f} ms [{t_min:.2f}] "
                         f"(fwd {t_fwd:.2f}), peak {mem / 2**20:.0f} MiB")
                if best is None or t < best[0]:
                    best = (t, t_fwd, packed)
            diff = (ours_fwd().image - peer_fwd(packed=best[2])[0]).abs()
            row.update(gsplat_ms=best[0], ratio=t_ours / best[0], fwd_ratio=t_ours_fwd / best[1],
                       image_max_diff=float(diff.max()), image_mean_diff=float(diff.mean()))
            line += (f"\n    ours / gsplat(best, packed={best[2]}): fwd+bwd {t_ours / best[0]:.3f}x, "
                     f"fwd {t_ours_fwd / best[1]:.3f}x; image |ours - gsplat| max "
                     f"{row['image_max_diff']:.2e}, mean {row['image_mean_diff']:.2e}")
        print(line, flush=True)
        rows.append(row)
        if args.profile:
            profile_kernels("ours", ours)
            if rasterization is not None:
                def peer_best(packed=best[2]):
                    img = rasterization(leaves[0], leaves[1], leaves[2], leaves[3], leaves[4],
                                        viewmat[None], K[None], w, h, near_plane=0.01,
                                        eps2d=0.3, packed=packed, tile_size=16)[0]
                    (img[0] * weight).sum().backward()

                profile_kernels(f"gsplat packed={best[2]}", peer_best)
    if args.out:
        Path(args.out).mkdir(parents=True, exist_ok=True)
        (Path(args.out) / "bm_cuda_kernels.json").write_text(json.dumps(
            {"gpu": gpu_name(), "width": w, "height": h, "rows": rows}, indent=1))


def object_masks(model, views, radius_frac: float = 0.25):
    """Visible masks of the Gaussians within a sphere around the scene's median point."""
    from cobgs.render.rasterize import rasterize

    means = model.means.detach()
    centre = means.median(0).values
    r = radius_frac * float((means - centre).norm(dim=-1).median())
    inside = ((means - centre).norm(dim=-1) < r).float()
    feats = torch.stack([inside, 1 - inside], -1)
    masks = []
    with torch.no_grad():
        for v in views:
            cam = v.camera
            out = rasterize(model.means, model.quats, model.scales, model.opacities, feats,
                            cam.viewmat, cam.K, cam.width, cam.height)
            masks.append(out.image[..., 0] > 0.5)
    return masks, int(inside.sum())


def bench_fern(args) -> None:
    from cobgs.data.colmap import read_colmap
    from cobgs.gaussians.ply import save_ply
    from cobgs.refine.alternation import refine
    from cobgs.configs import RefineConfig
    from cobgs.data.sfm import run_sfm
    from cobgs.configs import SfmOptions
    from cobgs.train.optimize import train
    from cobgs.configs import TrainConfig

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    report = {"gpu": gpu_name(), "torch": torch.__version__}
    print(f"GPU: {report['gpu']}", flush=True)
    sfm_dir = out / "fern_sfm"
    t = time.perf_counter()
    if not (sfm_dir / "sparse" / "0").is_dir():
        res = run_sfm(args.images, sfm_dir, SfmOptions(matcher="exhaustive", seed=0))
        print(f"SfM: {len(res.registered)} registered, {res.num_points3d} points", flush=True)
    report["sfm_s"] = time.perf_counter() - t
    scene = read_colmap(sfm_dir, test_every=0)
    dev = torch.device("cuda")
    for v in scene.train:
        v.camera = v.camera.to(dev)
        v.image = v.image.to(dev)
    w, h = scene.train[0].camera.width, scene.train[0].camera.height
    print(f"fern: {len(scene.train)} views at {w}x{h}, {len(scene.points)} SfM points "
          f"(SfM {report['sfm_s']:.1f} s)", flush=True)
    cfg = TrainConfig(iterations=args.iterations, log_interval_its=1000)
    torch.cuda.reset_peak_memory_stats()
    t0 = time.perf_counter()
    last = [t0]

    def progress(trainer, info):
        if trainer.iteration % 1000 == 0:
            now = time.perf_counter()
            eta = (now - t0) / trainer.iteration * (cfg.iterations - trainer.iteration)
            print(f"  train it {trainer.iteration}/{cfg.iterations}: loss {info['loss']:.4f}, "
                  f"psnr {info['psnr']:.2f}, {len(trainer.model)} Gaussians, "
                  f"{(now - last[0]):.1f} s / 1000 its, ETA {eta:.0f} s", flush=True)
            last[0] = now

    res = train(scene, cfg, progress=False, evaluate_test=False, callback=progress)
    torch.cuda.synchronize()
    report["train_s"] = time.perf_counter() - t0
    report["train_peak_gpu_mem"] = torch.cuda.max_memory_allocated()
    report["num_gaussians"] = len(res.model)
    report["train_psnr_last"] = res.history[-1]["psnr"] if res.history else None
    report["train_history"] = res.history
    print(f"train: {report['train_s']:.1f} s, {len(res.model)} Gaussians, peak GPU memory "
          f"{report['train_peak_gpu_mem'] / 2**30:.2f} GiB", flush=True)
    save_ply(out / "fern.ply", res.model.clone().to(torch.device("cpu")))
    cam = scene.train[0].camera  # for the parity tests (COBGS_TRAINED_PLY)
    (out / "fern.ply.camera.json").write_text(json.dumps(
        {"viewmat": cam.viewmat.tolist(), "K": cam.K.tolist(), "width": cam.width,
         "height": cam.height}))
    masks, n_obj = object_masks(res.model, scene.train)
    print(f"object: {n_obj} Gaussians; mask coverage "
          f"{float(torch.stack(masks).float().mean()):.3f}", flush=True)
    rcfg = RefineConfig(scene_type="forward")
    torch.cuda.reset_peak_memory_stats()
    t0 = time.perf_counter()
    r = refine(res.model, scene.train, masks, scene.extent, rcfg, progress=False,
               object_name="centre", texture_moments=res.adam_moments)
    torch.cuda.synchronize()
    report["refine_s"] = time.perf_counter() - t0
    report["refine_iterations"] = sum(s.iterations for s in r.stages) if hasattr(
        r.stages[0], "iterations") else None
    report["refine_peak_gpu_mem"] = torch.cuda.max_memory_allocated()
    report["refine_gaussians"] = [r.num_gaussians_start, r.num_gaussians_end]
    print(f"refine (forward, {len(scene.train)} views, {report['refine_iterations']} its): "
          f"{report['refine_s']:.1f} s, Gaussians {r.num_gaussians_start} -> "
          f"{r.num_gaussians_end}, peak GPU memory {report['refine_peak_gpu_mem'] / 2**30:.2f} GiB",
          flush=True)
    (out / "bm_cuda_fern.json").write_text(json.dumps(report, indent=1, default=str))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    k = sub.add_parser("kernels")
    k.add_argument("--sizes", default="100000,1000000")
    k.add_argument("--width", type=int, default=1008)
    k.add_argument("--height", type=int, default=756)
    k.add_argument("--reps", type=int, default=20)
    k.add_argument("--out", default="")
    k.add_argument("--profile", action="store_true", help="per-kernel times (torch.profiler)")
    f = sub.add_parser("fern")
    f.add_argument("--images", required=True, type=Path)
    f.add_argument("--iterations", type=int, default=30_000)
    f.add_argument("--out", required=True)
    args = ap.parse_args()
    if not torch.cuda.is_available():
        sys.exit("no CUDA device")
    {"kernels": bench_kernels, "fern": bench_fern}[args.cmd](args)


if __name__ == "__main__":
    main()
