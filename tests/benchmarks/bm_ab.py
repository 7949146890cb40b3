"""Builds side by side: the native kernels and a whole training step of several source
trees (or environment settings), alternated in one run, as ratios to a machine probe
(issue 26, part 3: "before / after as ratios measured in one run").

Usage (not collected by pytest), e.g. the last commit against the working tree::

    git worktree add /tmp/cobgs_base HEAD
    .venv/bin/python tests/benchmarks/bm_ab.py \\
        --checkpoint runs/bm_cost/ckpt/ckpt_30000.pt --sfm-dir runs/bm_cost/fern_sfm \\
        --variant base=/tmp/cobgs_base --variant new=. \\
        [--variant thp=.:THP_MEM_ALLOC_ENABLE=1] [--rounds 3] [--reps 8] [--write out.md]

A variant is ``NAME=TREE[:VAR=VALUE,...]``: the ``cobgs`` package (and so the ``csrc/``
kernels, built into the extension cache on first use) of the checkout TREE, with the
environment variables given. Every round runs every variant once, each in a fresh process,
in an order rotated from round to round, so that a slow spell of the machine falls on all
of them. A process times, ``--reps`` times over, on the checkpoint's model at one training
view (``--view``): ``bin_tiles_tight``, the ``blend`` forward and its backward (the ops
alone, the same inputs each time), then one whole ``Trainer.step`` (densification off, as
in bm_train_iter.py, views drawn in the same order in every process), each followed by
bm_train_iter.py's machine probe. Every time is divided by the probe measured next to it;
a variant's figure is the median of its rounds' median ratios, compared with the first
variant's.

Bit identity: each process hashes the three ops' outputs and the whole model (and Adam's
state) after its training steps; the table says whether they equal the first variant's.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
PARTS = ("bin", "fwd", "bwd", "step")


def _hash(h, tensors) -> None:
    import torch

    for t in tensors:
        h.update(t.detach().contiguous().view(-1).view(torch.uint8).numpy().tobytes())


def child(args) -> int:
    """One process: one variant's timings, printed as a JSON line."""
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    sys.path.insert(0, str(Path(args.tree).resolve()))
    import torch

    torch.set_num_threads(args.threads)
    # The variant's cobgs first: bm_train_iter puts this checkout's root on sys.path.
    import cobgs
    from cobgs.render import ops
    from cobgs.train.optimize import Trainer, load_model
    from cobgs.configs import TrainConfig

    sys.path.insert(1, str(HERE))
    from bm_train_iter import MachineProbe, load_scene

    scene = load_scene("fern", Path(args.sfm_dir))
    model = load_model(args.checkpoint)
    trainer = Trainer(scene, TrainConfig(iterations=30_000), model)
    trainer.model.active_sh_degree = trainer.model.sh_degree
    trainer.iteration = max(trainer.sched.densify_until, 15_000) + 1  # plain steps
    if not 0 <= args.view < len(scene.train):
        raise SystemExit(f"--view {args.view}: the scene has training views 0..{len(scene.train) - 1}")
    cam = scene.train[args.view].camera
    m = trainer.model
    w, h = cam.width, cam.height
    bg = trainer.background
    with torch.no_grad():
        d = m.data
        feats = m.colors(cam.center).detach().contiguous()
        m2, con, dep, radii = ops.project(d["means"].detach(), d["quats"].detach(), m.scales.detach(),
                                          cam.viewmat, cam.K, w, h)
        op = m.opacities.detach().contiguous()
    ops_out = {}

    def binning():
        ops_out["bin"] = ops.bin_tiles_tight(m2, radii, dep, con, op, w, h)

    def fwd():
        off, ids, prep = ops_out["bin"]
        ops_out["fwd"] = ops.blend(m2, con, op, feats, bg, off, ids, w, h, prep=prep)

    g = torch.Generator().manual_seed(0)
    v_img = torch.randn(h, w, feats.shape[1], generator=g) * 1e-3
    v_tr = torch.randn(h, w, generator=g) * 1e-3

    def bwd():
        off, ids, prep = ops_out["bin"]
        _, trans, nc, _, _ = ops_out["fwd"]
        ops_out["bwd"] = torch.ops.cobgs.blend_bwd(m2, con, op, feats, bg, off, ids, trans, nc, v_img,
                                                   v_tr, prep, True)

    with torch.no_grad():  # warm-up: extension load, buffers
        binning()
        fwd()
        bwd()
    trainer.step()
    probe = MachineProbe()
    times = {k: [] for k in PARTS}
    probes = []
    for _ in range(args.reps):
        with torch.no_grad():
            for k, f in (("bin", binning), ("fwd", fwd), ("bwd", bwd)):
                t0 = time.perf_counter()
                f()
                times[k].append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        trainer.step()
        times["step"].append(time.perf_counter() - t0)
        probes.append(probe.run())
    h_ops, h_model = hashlib.sha256(), hashlib.sha256()
    _hash(h_ops, [*ops_out["bin"], *ops_out["fwd"][:3], *ops_out["bwd"]])
    _hash(h_model, [t for _, t in sorted(trainer.model.data.items())])
    for group in trainer.optimizer.param_groups:
        for p in group["params"]:
            st = trainer.optimizer.state.get(p, {})
            _hash(h_model, [st[k] for k in ("exp_avg", "exp_avg_sq") if k in st])
    rec = {"ms": {k: 1e3 * statistics.median(v) for k, v in times.items()},
           "ratio": {k: statistics.median(t / p for t, p in zip(v, probes)) for k, v in times.items()},
           "probe_ms": 1e3 * statistics.median(probes), "ops_hash": h_ops.hexdigest()[:16],
           "model_hash": h_model.hexdigest()[:16], "gaussians": len(trainer.model),
           "cobgs": str(Path(cobgs.__file__).resolve().parent), "load": os.getloadavg()[0]}
    print(json.dumps(rec), flush=True)
    return 0


def parse_variant(spec: str):
    name, _, rest = spec.partition("=")
    tree, _, env = rest.partition(":")
    if not name or not tree:
        raise SystemExit(f"--variant {spec!r}: expected NAME=TREE[:VAR=VALUE,...]")
    if not (Path(tree) / "cobgs" / "__init__.py").is_file():
        raise SystemExit(f"--variant {spec!r}: {tree} is not a cobgs checkout (no cobgs/__init__.py)")
    pairs = dict(kv.split("=", 1) for kv in env.split(",") if kv) if env else {}
    return name, tree, pairs


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--checkpoint", type=Path, required=True)
    ap.add_argument("--sfm-dir", type=Path, required=True)
    ap.add_argument("--variant", action="append", default=[], help="NAME=TREE[:VAR=VALUE,...]")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--reps", type=int, default=8)
    ap.add_argument("--view", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--write", type=Path, default=None, help="also write the Markdown table here")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--tree", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        return child(args)
    if len(args.variant) < 2:
        raise SystemExit("give at least two --variant NAME=TREE[:VAR=VALUE,...]")
    if not args.checkpoint.is_file():
        raise SystemExit(f"{args.checkpoint}: no such checkpoint (bm_cost.py scene writes them)")
    variants = [parse_variant(v) for v in args.variant]
    names = [name for name, _, _ in variants]
    if len(set(names)) != len(names):
        raise SystemExit(f"--variant names must differ (their rounds are pooled by name), got {names}")
    results = {name: [] for name, _, _ in variants}
    for r in range(args.rounds):
        order = variants[r % len(variants):] + variants[:r % len(variants)]
        for name, tree, env in order:
            cmd = [sys.executable, str(Path(__file__).resolve()), "--child", "--tree", tree,
                   "--checkpoint", str(args.checkpoint), "--sfm-dir", str(args.sfm_dir),
                   "--reps", str(args.reps), "--view", str(args.view), "--threads", str(args.threads)]
            proc = subprocess.run(cmd, env={**os.environ, **env}, capture_output=True, text=True)
            if proc.returncode != 0:
                sys.stderr.write(proc.stdout + proc.stderr)
                raise SystemExit(f"variant {name} failed (exit {proc.returncode})")
            rec = json.loads(proc.stdout.strip().splitlines()[-1])
            results[name].append(rec)
            print(f"round {r + 1}/{args.rounds} {name}: " +
                  ", ".join(f"{k} {rec['ms'][k]:.1f} ms" for k in PARTS) +
                  f", probe {rec['probe_ms']:.2f} ms, load {rec['load']:.2f}", flush=True)
    ref = variants[0][0]

    def fig(name, k):
        return statistics.median(rec["ratio"][k] for rec in results[name])

    lines = [f"Checkpoint `{args.checkpoint.name}` ({results[ref][0]['gaussians']:,} Gaussians), view "
             f"{args.view}, {args.threads} threads, {args.rounds} rounds x {args.reps} reps "
             f"(`tests/benchmarks/bm_ab.py`). Time / probe, median of the rounds' medians; in brackets "
             f"the ratio to `{ref}` (below 1: faster). Median milliseconds in the last columns.", "",
             "| variant | tree | env | bin_tiles_tight | blend fwd | blend bwd | training step | ops output | "
             "model after the steps | ms (bin / fwd / bwd / step) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name, tree, env in variants:
        cells = []
        for k in PARTS:
            cells.append(f"{fig(name, k):.2f} ({fig(name, k) / fig(ref, k):.3f})")
        same_ops = all(rec["ops_hash"] == results[ref][0]["ops_hash"] for rec in results[name])
        same_model = all(rec["model_hash"] == results[ref][0]["model_hash"] for rec in results[name])
        ms = " / ".join(f"{statistics.median(rec['ms'][k] for rec in results[name]):.1f}" for k in PARTS)
        env_s = ", ".join(f"{k}={v}" for k, v in env.items()) or "-"
        lines.append(f"| {name} | `{tree}` | {env_s} | " + " | ".join(cells) +
                     f" | {'same' if same_ops else 'DIFFERENT'} | {'same' if same_model else 'DIFFERENT'} | {ms} |")
    text = "\n".join(lines)
    print(text)
    if args.write:
        args.write.parent.mkdir(parents=True, exist_ok=True)
        args.write.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
