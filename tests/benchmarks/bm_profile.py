"""Where the time of a render and of a training step goes (issue 10's profile, reproducible).

Usage::

    .venv/bin/python tests/benchmarks/bm_profile.py                          # bm scene, 1 thread
    .venv/bin/python tests/benchmarks/bm_profile.py --scene fern --ply /tmp/cobgs_bm_train/fern.ply
    .venv/bin/python tests/benchmarks/bm_profile.py --scene fern --threads 2 --train-steps 5

Builds (once, cached apart from the normal build) the extension with ``-DCOBGS_PROFILE``:
per-phase thread-CPU timers and pair counters inside the kernels, printed by the library
when the process exits, summed over every call (the number of calls is printed with them).
This script then

1. times each rasterizer op on its own (median wall and process CPU of ``--reps`` calls):
   project, bin_tiles_tight (per-Gaussian records, depth sort, tight tile lists), blend,
   blend_bwd, project_bwd;
2. prints the per-view blend statistics: tile-list entries, 8-pixel blocks evaluated and
   reaching exp, and (Gaussian, pixel) pairs blended, per pixel;
3. for a trained scene (``--ply``), profiles ``--train-steps`` training steps with
   ``torch.profiler`` (SH colour, loss, Adam and Python overhead around the ops).

Scenes: ``bm`` is bm_rasterize.py's 100k-Gaussian 504x378 scene; ``fern`` / ``lego`` take
the first training view of the scene bm_train_iter.py loads and a trained PLY.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

# Before cobgs builds or loads anything: the instrumented build, in its own cache folder.
os.environ.setdefault("COBGS_PROFILE", "1")
os.environ.setdefault("COBGS_EXT_DIR", str(Path.home() / ".cache" / "cobgs" / "ext_profile"))
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(Path(__file__).resolve().parent))


def view_tensors(args):
    """(means, quats, scales, opacities, features, viewmat, K, W, H, v_image, v_trans, trainer)."""
    g = torch.Generator().manual_seed(0)
    if args.scene == "bm":
        import bm_rasterize as R

        (means, quats, scales, op, feat, vm, K), _, gi, ga = R.make_scene(100_000, 0)
        return means, quats, scales, op, feat, vm, K, R.W, R.H, gi, ga, None
    import bm_train_iter as B
    from cobgs.train.optimize import Trainer, load_model
    from cobgs.configs import TrainConfig

    scene = B.load_scene(args.scene, args.sfm_dir)
    model = load_model(args.ply)
    model.active_sh_degree = model.sh_degree
    cam = scene.train[0].camera
    w, h = int(cam.width), int(cam.height)
    with torch.no_grad():
        feats = model.colors(cam.center).contiguous()
    t = [model.means.detach(), model.quats.detach(), model.scales.detach(), model.opacities.detach()]
    trainer = Trainer(scene, TrainConfig(iterations=30_000), model)
    trainer.iteration = max(trainer.sched.densify_until, 15_000) + 1  # plain steps
    return (*[x.contiguous() for x in t], feats, cam.viewmat.float(), cam.K.float(), w, h,
            torch.randn(h, w, 3, generator=g), torch.randn(h, w, generator=g), trainer)


def timed(fn, reps):
    walls, cpus, out = [], [], None
    for _ in range(reps):
        w0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        walls.append(time.perf_counter() - w0)
        cpus.append(time.process_time() - c0)
    return out, 1000 * statistics.median(walls), 1000 * statistics.median(cpus)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", choices=["bm", "fern", "lego"], default="bm")
    ap.add_argument("--ply", type=Path, default=None, help="trained PLY (fern / lego)")
    ap.add_argument("--sfm-dir", type=Path, default=Path("/tmp/cobgs_bm_train/fern_sfm"))
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--train-steps", type=int, default=5)
    args = ap.parse_args(argv)
    if args.scene != "bm" and args.ply is None:
        args.ply = Path("/tmp/cobgs_bm_train") / f"{args.scene}.ply"
    torch.set_num_threads(args.threads)
    from cobgs.render import ops

    ops.ensure_loaded()
    means, quats, scales, op, feat, vm, K, w, h, gi, ga, trainer = view_tensors(args)
    P = torch.ops.cobgs
    bg = torch.zeros(feat.shape[1])
    (m2, co, d, r), pw, pc = timed(lambda: P.project(means, quats, scales, vm, K, w, h, 0.01), args.reps)
    (off, ids, prep), bw, bc = timed(lambda: P.bin_tiles_tight(m2, r, d, co, op, w, h), args.reps)
    (_, tr, nc, _, _), fw, fc = timed(lambda: P.blend(m2, co, op, feat, bg, off, ids, w, h, None, 2, prep),
                                      args.reps)
    grads, bbw, bbc = timed(lambda: P.blend_bwd(m2, co, op, feat, bg, off, ids, tr, nc, gi, -ga, prep),
                            args.reps)
    _, pbw, pbc = timed(lambda: P.project_bwd(means, quats, scales, vm, K, w, h, r, grads[0], grads[1],
                                              torch.zeros_like(d)), args.reps)
    pix = w * h
    full = P.bin_tiles(m2, r, d, w, h)[1].numel()
    print(f"scene {args.scene} {w}x{h}, {means.shape[0]} Gaussians ({int((r > 0).sum())} in view), "
          f"threads {args.threads}, load {os.getloadavg()[0]:.1f}")
    print(f"tile-list entries {ids.numel()} tight ({full} with 3-sigma boxes): "
          f"{ids.numel() * 256 / pix:.1f} candidates per pixel; last contributor rank per pixel "
          f"mean {nc.float().mean():.1f}")
    print("per op, median of", args.reps, "(wall / process CPU ms):")
    for name, a, b in [("project", pw, pc), ("bin_tiles_tight", bw, bc), ("blend", fw, fc),
                       ("blend_bwd", bbw, bbc), ("project_bwd", pbw, pbc)]:
        print(f"  {name:16s} {a:8.2f} / {b:8.2f}")
    if trainer is not None and args.train_steps > 0:
        from torch.profiler import ProfilerActivity, profile

        for _ in range(2):
            trainer.step()
        with profile(activities=[ProfilerActivity.CPU]) as prof:
            for _ in range(args.train_steps):
                trainer.step()
        print(f"training steps ({args.train_steps}, torch.profiler, self CPU of the calling thread):")
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=18))
    calls = args.reps + 1 + (args.train_steps + 2 if trainer is not None else 0)
    print(f"The instrumented kernels print their totals at exit (about {calls} calls of each op; "
          f"divide by 'calls ...'): phase thread-CPU ms, and blocks / pairs counted in the "
          f"blend passes (pairs blended / calls / {pix} pixels = pairs per pixel).", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
