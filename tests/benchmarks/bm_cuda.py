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


def frustum_scene(n: int, width: int, height: int, seed: int = 0, channels: int = 4):
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
    colors = torch.rand(n, channels, generator=g)
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
    """Every size x channel count x path (exact / fast: csrc/blend/blend_cuda.cuh) against gsplat.
    With 1 channel ours also counts the pixels of 2 labels per Gaussian (what COB-GS's mask
    stages render); gsplat renders the channel alone."""
    import itertools

    from cobgs.render.ops import cuda_fast_path

    rows = []
    for channels, path in itertools.product([int(c) for c in args.channels.split(",")], args.paths.split(",")):
        if path not in ("exact", "fast"):
            raise SystemExit(f"--paths: exact and / or fast, got {path!r}")
        with cuda_fast_path(path == "fast"):
            rows += _bench_kernels(args, channels, path)
    if args.out:
        Path(args.out).mkdir(parents=True, exist_ok=True)
        (Path(args.out) / "bm_cuda_kernels.json").write_text(json.dumps(
            {"gpu": gpu_name(), "torch": torch.__version__, "gsplat": _gsplat_version(),
             "width": args.width, "height": args.height, "rows": rows}, indent=1))


def _gsplat_version():
    try:
        import gsplat

        return gsplat.__version__
    except Exception:  # noqa: BLE001 - absent or unbuildable: the rows say so
        return None


def _bench_kernels(args, channels: int, path: str) -> list:
    import cobgs

    w, h = args.width, args.height
    labels_on = channels == 1
    print(f"GPU: {gpu_name()}; torch {torch.__version__}; {w}x{h}, {channels} channel(s)"
          + (" + 2-label pixel counts (ours)" if labels_on else "")
          + f", {path} path, median of {args.reps} (min in brackets)")
    try:
        import gsplat
        from gsplat import rasterization
        print(f"gsplat {gsplat.__version__}")
    except Exception as exc:  # noqa: BLE001 - report why the peer is missing
        rasterization = None
        print(f"gsplat not available: {exc}")
    rows = []
    for n in (int(s) for s in args.sizes.split(",")):
        means, quats, scales, opac, colors, viewmat, K = frustum_scene(n, w, h, channels=channels)
        weight = torch.rand(h, w, channels, device="cuda", generator=torch.Generator("cuda").manual_seed(1))
        leaves = [t.clone().requires_grad_() for t in (means, quats, scales, opac, colors)]
        lab = (torch.rand(h, w, device="cuda", generator=torch.Generator("cuda").manual_seed(2)) < 0.3).int() \
            if labels_on else None

        def ours():
            for t in leaves:
                t.grad = None
            out = cobgs.rasterize(*leaves, viewmat, K, w, h, pixel_labels=lab, num_labels=2)
            (out.image * weight).sum().backward()
            return out

        def ours_fwd():
            with torch.no_grad():
                return cobgs.rasterize(*leaves, viewmat, K, w, h, pixel_labels=lab, num_labels=2)

        torch.cuda.reset_peak_memory_stats()
        t_ours, t_ours_min = time_cuda(ours, args.reps)
        mem_ours = torch.cuda.max_memory_allocated()
        t_ours_fwd, _ = time_cuda(ours_fwd, args.reps)
        row = {"n": n, "channels": channels, "path": path, "labels": labels_on, "ours_ms": t_ours,
               "ours_min_ms": t_ours_min, "ours_fwd_ms": t_ours_fwd, "ours_peak_mem": mem_ours}
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
    return rows


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


def pack_fern(args) -> None:
    """Write the SfM'd scene as cameras, names, split and points (``torch.save``), so that a
    machine without pycolmap (the GPU machine) trains on exactly this scene: ``fern --scene``
    reads it and the undistorted images from ``--images-dir`` (the SfM folder's ``images/``)."""
    from cobgs.data.colmap import read_colmap

    scene = read_colmap(args.sfm_dir, test_every=args.test_every)
    pack = {"train": [(v.name, Path(v.path).name, v.camera) for v in scene.train],
            "test": [(v.name, Path(v.path).name, v.camera) for v in scene.test],
            "points": scene.points, "points_rgb": scene.points_rgb, "extent": scene.extent,
            "init_bounds": scene.init_bounds, "background": scene.background,
            "notes": scene.notes, "source": str(args.sfm_dir), "test_every": args.test_every}
    torch.save(pack, args.out)
    print(f"{args.out}: {len(scene.train)} train / {len(scene.test)} held-out views, "
          f"{len(scene.points)} points")


def _unpack_fern(path: Path, images_dir: Path):
    from cobgs.data.scene import Scene, View, load_rgb

    pack = torch.load(path, weights_only=False)

    def views(rows):
        out = []
        for name, file, cam in rows:
            image, _ = load_rgb(images_dir / file, (cam.width, cam.height))
            out.append(View(cam, image, name, path=str(images_dir / file)))
        return out

    return Scene(train=views(pack["train"]), test=views(pack["test"]), extent=pack["extent"],
                 points=pack["points"], points_rgb=pack["points_rgb"],
                 init_bounds=pack["init_bounds"], background=tuple(pack["background"]),
                 source=pack["source"], kind="colmap", notes=list(pack["notes"]))


def _profile_since(whole: dict, before: dict) -> dict:
    """The step profile of the steps between two reports of one timer (cobgs.train.profile)."""
    steps = whole["steps"] - before["steps"]
    ms = {p: v["ms_per_step"] * whole["steps"] - before["phases"][p]["ms_per_step"] * before["steps"]
          for p, v in whole["phases"].items()}
    total = sum(ms.values())
    return {"steps": steps, "device": whole["device"], "ms_per_step": total / max(steps, 1),
            "phases": {p: {"ms_per_step": t / max(steps, 1), "share": t / total if total else 0.0,
                           "calls": whole["phases"][p]["calls"] - before["phases"][p]["calls"]}
                       for p, t in ms.items()}}


def bench_fern(args) -> None:
    from cobgs.configs import RefineConfig, SfmOptions, TrainConfig
    from cobgs.data.colmap import read_colmap
    from cobgs.gaussians.ply import save_ply
    from cobgs.refine.alternation import refine
    from cobgs.render.ops import cuda_fast_path
    from cobgs.train.optimize import train

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    report = {"gpu": gpu_name(), "torch": torch.__version__, "path": args.path,
              "recipe": args.recipe, "iterations": args.iterations, "rasterizer": args.rasterizer}
    if args.rasterizer == "gsplat":
        import gsplat

        report["gsplat"] = gsplat.__version__
    print(f"GPU: {report['gpu']}; CUDA blending path: {args.path}", flush=True)
    t = time.perf_counter()
    if args.scene is not None:
        scene = _unpack_fern(args.scene, args.images_dir)
    else:
        from cobgs.data.sfm import run_sfm

        sfm_dir = out / "fern_sfm"
        if not (sfm_dir / "sparse" / "0").is_dir():
            res = run_sfm(args.images, sfm_dir, SfmOptions(matcher="exhaustive", seed=0))
            print(f"SfM: {len(res.registered)} registered, {res.num_points3d} points", flush=True)
        scene = read_colmap(sfm_dir, test_every=args.test_every)
    report["load_s"] = time.perf_counter() - t
    dev = torch.device("cuda")
    for v in scene.train + scene.test:
        v.camera = v.camera.to(dev)
        v.image = v.image.to(dev)
    w, h = scene.train[0].camera.width, scene.train[0].camera.height
    print(f"fern: {len(scene.train)} train / {len(scene.test)} held-out views at {w}x{h}, "
          f"{len(scene.points)} SfM points ({report['load_s']:.1f} s)", flush=True)
    kw = {"iterations": args.iterations} if args.iterations else {}
    if args.recipe != "3dgs":
        kw["recipe"] = args.recipe
    cfg = TrainConfig(log_interval_its=1000, rasterizer=args.rasterizer, **kw)
    its = cfg.iterations
    report["iterations"] = its
    torch.cuda.reset_peak_memory_stats()
    t0 = time.perf_counter()
    last = [t0]

    from cobgs.train.profile import PhaseTimer

    timers = {}

    def progress(trainer, info):
        if args.profile_last and trainer.iteration == 1:
            timers["timer"] = trainer.timer = PhaseTimer(dev)
        if args.profile_last and trainer.iteration == max(1, its - args.profile_last):
            timers["before_last"] = trainer.timer.report()  # (one synchronisation)
        if trainer.iteration % 1000 == 0:
            torch.cuda.synchronize()
            now = time.perf_counter()
            eta = (now - t0) / trainer.iteration * (its - trainer.iteration)
            print(f"  train it {trainer.iteration}/{its}: loss {info['loss']:.4f}, "
                  f"psnr {info['psnr']:.2f}, {len(trainer.model)} Gaussians, "
                  f"{(now - last[0]):.1f} s / 1000 its, ETA {eta:.0f} s", flush=True)
            last[0] = now

    with cuda_fast_path(args.path == "fast"):
        res = train(scene, cfg, progress=False, evaluate_test=False, callback=progress)
        torch.cuda.synchronize()
        report["train_s"] = time.perf_counter() - t0
        report["train_peak_gpu_mem"] = torch.cuda.max_memory_allocated()
        report["num_gaussians"] = len(res.model)
        report["train_psnr_last"] = res.history[-1]["psnr"] if res.history else None
        report["train_history"] = res.history
        if timers:
            whole = timers["timer"].report()
            report["profile"] = {"whole": whole}
            if "before_last" in timers:
                report["profile"]["last"] = _profile_since(whole, timers["before_last"])
            for k, rep in report["profile"].items():
                print(f"step profile ({k}, {rep['steps']} steps): {rep['ms_per_step']:.2f} ms/step: "
                      + ", ".join(f"{p} {v['ms_per_step']:.2f}" for p, v in rep["phases"].items()), flush=True)
        print(f"train: {report['train_s']:.1f} s, {len(res.model)} Gaussians, peak GPU memory "
              f"{report['train_peak_gpu_mem'] / 2**30:.2f} GiB", flush=True)
    if scene.test:  # held-out PSNR, rendered with the exact path for both trainings
        from cobgs.train.optimize import evaluate

        with cuda_fast_path(False):
            ev = evaluate(res.model, scene.test, list(scene.background), cfg.backend)
        report["test_psnr"], report["test_ssim"] = ev["psnr"], ev["ssim"]
        print(f"held-out ({len(scene.test)} views): PSNR {ev['psnr']:.3f}, SSIM {ev['ssim']:.4f}",
              flush=True)
    (out / "bm_cuda_fern.json").write_text(json.dumps(report, indent=1, default=str))
    if args.save_ply:
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
    with cuda_fast_path(args.path == "fast"):
        r = refine(res.model, scene.train, masks, scene.extent, rcfg, progress=False,
                   object_name="centre", texture_moments=res.adam_moments)
        torch.cuda.synchronize()
    report["refine_s"] = time.perf_counter() - t0
    report["refine_peak_gpu_mem"] = torch.cuda.max_memory_allocated()
    report["refine_gaussians"] = [r.num_gaussians_start, r.num_gaussians_end]
    print(f"refine (forward, {len(scene.train)} views): {report['refine_s']:.1f} s, Gaussians "
          f"{r.num_gaussians_start} -> {r.num_gaussians_end}, peak GPU memory "
          f"{report['refine_peak_gpu_mem'] / 2**30:.2f} GiB", flush=True)
    (out / "bm_cuda_fern.json").write_text(json.dumps(report, indent=1, default=str))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    k = sub.add_parser("kernels")
    k.add_argument("--sizes", default="100000,1000000")
    k.add_argument("--width", type=int, default=1008)
    k.add_argument("--height", type=int, default=756)
    k.add_argument("--reps", type=int, default=20)
    k.add_argument("--channels", default="4,1", help="feature channels (1: with 2-label pixel counts, as "
                   "COB-GS's mask stages render)")
    k.add_argument("--paths", default="exact,fast", help="the CUDA blending paths to time (exact, fast)")
    k.add_argument("--out", default="")
    k.add_argument("--profile", action="store_true", help="per-kernel times (torch.profiler)")
    f = sub.add_parser("fern")
    src = f.add_mutually_exclusive_group(required=True)
    src.add_argument("--images", type=Path, help="the 20 images (SfM with pycolmap first)")
    src.add_argument("--scene", type=Path, help="a scene written by pack-fern (no pycolmap needed)")
    f.add_argument("--images-dir", type=Path, help="with --scene: the SfM folder's images/")
    f.add_argument("--test-every", type=int, default=8, help="held-out views (with --images)")
    f.add_argument("--iterations", type=int, default=0, help="0: the recipe's (3dgs: 30 000)")
    f.add_argument("--recipe", default="3dgs", help="TrainConfig.recipe")
    f.add_argument("--path", choices=("exact", "fast"), default="exact", help="the CUDA blending path")
    f.add_argument("--rasterizer", choices=("ours", "gsplat"), default="ours",
                   help="TrainConfig.rasterizer of the training steps (gsplat: its rasterization; evaluation and "
                        "refinement stay ours)")
    f.add_argument("--profile-last", type=int, default=2000,
                   help="the step profile (CUDA events per phase, cobgs.train.profile) of the whole run and of its "
                        "last N iterations, once the model has grown (0: no profile)")
    f.add_argument("--save-ply", action="store_true", help="write fern.ply (for COBGS_TRAINED_PLY)")
    f.add_argument("--out", required=True)
    pk = sub.add_parser("pack-fern", help="(any machine) write an SfM'd scene for fern --scene")
    pk.add_argument("--sfm-dir", required=True, type=Path)
    pk.add_argument("--test-every", type=int, default=8)
    pk.add_argument("--out", required=True, type=Path)
    args = ap.parse_args()
    if args.cmd == "pack-fern":
        return pack_fern(args)
    if args.cmd == "fern" and args.scene is not None and args.images_dir is None:
        ap.error("--scene needs --images-dir")
    if not torch.cuda.is_available():
        sys.exit("no CUDA device")
    {"kernels": bench_kernels, "fern": bench_fern}[args.cmd](args)


if __name__ == "__main__":
    main()
