"""Time of one 3DGS training iteration (render + loss + backward + Adam) with cobgs.train.optimize.

Usage::

    .venv/bin/python tests/benchmarks/bm_train_iter.py                     # fern 1/8
    .venv/bin/python tests/benchmarks/bm_train_iter.py --ply /tmp/cobgs_bm_train/fern.ply
    .venv/bin/python tests/benchmarks/bm_train_iter.py --scene lego --ply /tmp/cobgs_bm_train/lego.ply

Scene: fern at 1/8 (504x378; SfM from ``--sfm-dir``, default the folder bm_train.py
writes, made with pycolmap when absent) or lego at 200x200. Model: a trained PLY
(``--ply``; default ``/tmp/cobgs_bm_train/<scene>.ply`` when it exists), else the
scene's own initialisation (SfM points, few large Gaussians: not representative of a
trained scene), or with ``--proxy N`` a stand-in for a trained model: every initial
Gaussian split into children sampled inside it (scales shrunk so the children fill
its volume), N in all, opacities uniform in [0.2, 0.9], random SH rest coefficients.
The proxy only approximates a trained scene's cost; the printed model line says which
was used. All SH degrees are active (degree 3), as after the first 3k
iterations of the recipe.

The iteration is :meth:`cobgs.train.optimize.Trainer.step` with densification and opacity reset
switched off (the trainer is placed past ``densify_until``), so every timed iteration
does the same work. Its parts are timed separately on the same views: SH colour,
rasterize forward, loss (0.8 L1 + 0.2 (1 - SSIM)) forward, backward (loss and
rasterizer), Adam step. The SH colour is the native ``cobgs::sh_colors`` op that
:func:`cobgs.render.image.render` uses on the CPU. Wall and process CPU time (all threads) are reported, with the
load average: on a machine shared with other jobs the wall time includes waiting for a
core.

A machine probe (a 384x384 float32 GEMM and one fused Adam step over 4M floats, about a
tenth of an iteration, compute- and memory-bound like the iteration) runs after every timed
step. Its spread (median / best) shows how much other jobs slowed the run, and the
iteration is also reported as a ratio to the probe measured next to it, scaled to the
probe's best time: the iteration time this build would take on the machine at its quietest
moment of the same run (the ratio, not the absolute time, is what compares builds).

Target (issue 10): a full iteration on fern 1/8 <= 120 ms (2 threads).
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "2")
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # see bm_rasterize.py

import torch  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _bench_util import Clock  # noqa: E402
SHARED = Path(os.environ.get("COBGS_SHARED_DATA", REPO.parent / "shared" / "data"))
BM_OUT = Path("/tmp/cobgs_bm_train")




def load_scene(kind: str, sfm_dir: Path):
    if kind == "lego":
        from cobgs.data.blender import read_blender

        return read_blender(SHARED / "nerf_synthetic_lego", downscale=4, background=(1.0, 1.0, 1.0))
    from cobgs.data.colmap import read_colmap

    if not (sfm_dir / "sparse" / "0").is_dir():
        from cobgs.data.sfm import run_sfm
        from cobgs.configs import SfmOptions

        run_sfm(SHARED / "llff_fern" / "images_8", sfm_dir, SfmOptions(matcher="exhaustive"))
    return read_colmap(sfm_dir, test_every=8)


def scene_cost(model, camera, background) -> str:
    """What a view of the model costs the blend: tile-list entries per pixel, how far the
    pixels get down their lists (last contributor's rank) and how opaque they end up."""
    from cobgs.render import ops

    with torch.no_grad():
        d = model.data
        feats = model.colors(camera.center).detach()
        m2, con, dep, radii = ops.project(d["means"].detach(), d["quats"].detach(), model.scales.detach(),
                                          camera.viewmat, camera.K, camera.width, camera.height)
        full = ops.bin_tiles(m2, radii, dep, camera.width, camera.height)[1].numel()
        off, ids, prep = ops.bin_tiles_tight(m2, radii, dep, con, model.opacities.detach(),
                                              camera.width, camera.height)
        _, trans, n_contrib, _, _ = ops.blend(m2, con, model.opacities.detach(), feats, background,
                                               off, ids, camera.width, camera.height, None, 2, prep)
    n_tiles = off.numel() - 1
    return (f"view {camera.name}: {int((radii > 0).sum())} Gaussians in view, "
            f"{ids.numel() / n_tiles:.0f} tile-list entries per tile ({full / n_tiles:.0f} with "
            f"3-sigma boxes), last contributor rank per "
            f"pixel mean {n_contrib.float().mean():.0f} (median {n_contrib.float().median():.0f}), "
            f"final transmittance median {trans.median():.4f}, mean opacity "
            f"{model.opacities.mean():.3f}")


def proxy_model(init, n: int, seed: int = 0):
    """A trained-size stand-in: ``init``'s Gaussians split into ``n`` children."""
    from cobgs.gaussians.model import GaussianModel, inverse_sigmoid

    g = torch.Generator().manual_seed(seed)
    d = {k: v.detach() for k, v in init.data.items()}
    m = d["means"].shape[0]
    parent = torch.randint(0, m, (n,), generator=g)
    k = n / m
    scales = torch.exp(d["log_scales"][parent])
    rot = init.rotations.detach()[parent]
    from cobgs.gaussians.model import quat_to_rotmat

    offs = torch.einsum("nij,nj->ni", quat_to_rotmat(rot), scales * torch.randn(n, 3, generator=g))
    means = d["means"][parent] + offs
    log_scales = d["log_scales"][parent] - math.log(k) / 3.0
    opac = 0.2 + 0.7 * torch.rand(n, generator=g)
    shN = 0.05 * torch.randn(n, d["shN"].shape[1], 3, generator=g)
    return GaussianModel(means=means, log_scales=log_scales, quats=d["quats"][parent],
                         opacity_logits=inverse_sigmoid(opac), sh0=d["sh0"][parent], shN=shN)


class MachineProbe:
    """A fixed small workload timed next to each step (see the module docstring)."""

    def __init__(self, n: int = 4_000_000, size: int = 384):
        g = torch.Generator().manual_seed(0)
        self.a = torch.rand(size, size, generator=g)
        self.b = torch.rand(size, size, generator=g)
        self.p = torch.nn.Parameter(torch.rand(n, generator=g))
        self.p.grad = torch.rand(n, generator=g) - 0.5
        self.opt = torch.optim.Adam([self.p], lr=1e-6, fused=True)
        self.run()  # allocate the moments

    def run(self) -> float:
        t0 = time.perf_counter()
        torch.mm(self.a, self.b)
        self.opt.step()
        return time.perf_counter() - t0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", choices=["fern", "lego"], default="fern")
    ap.add_argument("--ply", type=Path, default=None)
    ap.add_argument("--sfm-dir", type=Path, default=BM_OUT / "fern_sfm")
    ap.add_argument("--proxy", type=int, default=0,
                    help="without a trained PLY: split the initial model into this many")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--reps", type=int, default=10, help="timed iterations")
    ap.add_argument("--random-background", action="store_true",
                    help="time the recipe's random-background iteration (for a PLY trained with it)")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)

    from cobgs.train import losses
    from cobgs.evaluate.ssim import ssim
    from cobgs.train.losses import l1_loss
    from cobgs.train.optimize import Trainer, load_model
    from cobgs.configs import TrainConfig

    scene = load_scene(args.scene, args.sfm_dir)
    ply = args.ply if args.ply is not None else BM_OUT / f"{args.scene}.ply"
    model = load_model(ply) if ply.is_file() else None
    config = TrainConfig(iterations=30_000, random_background=args.random_background)
    trainer = Trainer(scene, config, model)
    what = str(ply) if ply.is_file() else "initialisation (no trained PLY: not representative)"
    if model is None and args.proxy > 0:
        trainer = Trainer(scene, config, proxy_model(trainer.model, args.proxy))
        what = f"proxy: initialisation split into {args.proxy} (no trained PLY)"
    trainer.model.active_sh_degree = trainer.model.sh_degree
    # Past densify_until: no densification, opacity reset or statistics; plain steps.
    trainer.iteration = max(trainer.sched.densify_until, 15_000) + 1
    view0 = scene.train[0]
    w, h = int(view0.camera.width), int(view0.camera.height)
    print(f"scene {args.scene} {w}x{h}, {len(scene.train)} training views, model "
          f"{what}"
          f", {len(trainer.model)} Gaussians, SH degree {trainer.model.active_sh_degree}, "
          f"threads {args.threads}, OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY')}")

    print(scene_cost(trainer.model, view0.camera, trainer.background))
    for _ in range(2):  # warm-up (extension load, allocator)
        trainer.step()
    load0 = os.getloadavg()
    # Record the views the timed steps draw, so the parts below are timed on the same ones
    # (the cost of a view varies with how much of the scene it sees).
    seen = []
    draw = trainer._next_view

    def recording_next_view():
        seen.append(draw())
        return seen[-1]

    trainer._next_view = recording_next_view
    probe = MachineProbe()
    steps, probes = [], []
    for _ in range(args.reps):
        with Clock() as c:
            trainer.step()
        steps.append(c)
        probes.append(probe.run())

    # The parts, on the same views, with the trainer's own model and optimizer.
    from cobgs.render import ops
    from cobgs.render.image import render

    model, opt = trainer.model, trainer.optimizer
    parts = {k: [] for k in ("sh colour", "rasterize fwd", "loss fwd", "backward", "adam")}
    for _, view in seen:
        cam = view.camera
        with Clock() as c_sh:
            if hasattr(ops, "sh_colors"):  # as render() does
                feats = ops.sh_colors(model.data["means"], model.data["sh0"],
                                       model.data["shN"], cam.center, model.active_sh_degree)
            else:  # an older checkout (before the native SH op), for comparisons
                feats = model.colors(cam.center)
        with Clock() as c_r:
            out = render(model, cam, trainer.background, features=feats)
            out.means2d.retain_grad()
        with Clock() as c_l:
            img = out.image
            if hasattr(losses, "_NativePhotometricLoss"):  # as Trainer.step does
                loss = losses.photometric_loss(img, view.image, config.ssim_weight)
            else:  # an older checkout, for comparisons
                loss = (1 - config.ssim_weight) * l1_loss(img, view.image) + \
                    config.ssim_weight * (1 - ssim(img, view.image))
        with Clock() as c_b:
            loss.backward()
        with Clock() as c_a:
            opt.step()
            opt.zero_grad(set_to_none=True)
        for k, c in zip(parts, (c_sh, c_r, c_l, c_b, c_a)):
            parts[k].append(c)

    def med(cs, attr):
        return 1000 * statistics.median(getattr(c, attr) for c in cs)

    print(f"full iteration (Trainer.step): wall {med(steps, 'wall'):.1f} ms, CPU "
          f"{med(steps, 'cpu'):.1f} ms (all threads), median of {args.reps}")
    total_w = total_c = 0.0
    for k, cs in parts.items():
        total_w += med(cs, "wall")
        total_c += med(cs, "cpu")
        print(f"  {k:14s} wall {med(cs, 'wall'):7.1f} ms   CPU {med(cs, 'cpu'):7.1f} ms")
    print(f"  {'sum of parts':14s} wall {total_w:7.1f} ms   CPU {total_c:7.1f} ms")
    p_med, p_best = 1000 * statistics.median(probes), 1000 * min(probes)
    ratio = statistics.median(c.wall / pr for c, pr in zip(steps, probes))
    print(f"machine probe after each step: median {p_med:.2f} ms, best {p_best:.2f} ms "
          f"(contention factor {p_med / p_best:.2f}); iteration / probe: median {ratio:.1f} "
          f"(compare builds with this ratio; times the probe's best it estimates "
          f"{ratio * p_best:.1f} ms for the quietest moment of the run)")
    print(f"load average {load0[0]:.1f} -> {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs; "
          f"target (issue 10): full iteration <= 120 ms wall on fern 1/8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
