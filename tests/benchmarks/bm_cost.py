"""What a whole NVOS-protocol scene costs on a CPU (issue 26): fern at 1008x756, and paper
Table 6 (prep / opt / seg time and peak memory) for COB-GS and the peers on it.

Run (not collected by pytest), on this repository's venv::

    # 1. SfM + 3DGS training, 30k iterations, checkpointed every 1000: resumable, so the
    #    hours it takes on 2 cores can be spread over several runs (--budget-s stops one
    #    cleanly at a checkpoint; the next run continues from the newest).
    .venv/bin/python tests/benchmarks/bm_cost.py scene --images ../shared/data/llff_fern/images_4 \\
        --out runs/bm_cost [--iterations 30000] [--budget-s 3600]
    # 2. Table 6 on a checkpoint of that run (masks written as PNG files, then read back:
    #    "masks from files"), each method in its own process so that its peak memory is its own.
    .venv/bin/python tests/benchmarks/bm_cost.py table6 --out runs/bm_cost [--checkpoint ckpt_30000.pt]
    # 3. The Markdown summary of both.
    .venv/bin/python tests/benchmarks/bm_cost.py summary --out runs/bm_cost [--write docs/benchmarks/cost_cpu.md]
    #    (--write replaces only the text between the file's <!-- bm_cost summary --> markers)
    # (a profile_<checkpoint>.txt in --out, bm_profile.py's output on that checkpoint, is
    #  appended to the summary)

Logged per 1000 iterations (``train_log.jsonl``): wall and CPU seconds, Gaussian count, the
load average, which run it belongs to. The object is the Gaussians within a sphere around
the scene's median point (its masks rendered from the trained scene), as in bm_cuda.py's fern
run: the NVOS annotations are not available offline, and a refinement's cost does not depend
on which object it is. Timings use 2 threads with passive OpenMP waiting.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "2")
os.environ.setdefault("OMP_WAIT_POLICY", "passive")

import argparse  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
METHODS = ("cobgs", "flashsplat", "sa3d", "nosplit", "ngs")


class _Budget(Exception):
    pass


def _peak_rss() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def _scene(out: Path, images: Path | None, test_every: int = 0, sfm_dir: Path | None = None):
    """The SfM'd scene (``out/fern_sfm``, or a shared ``sfm_dir`` so that two recipes train on
    the same reconstruction); ``test_every`` = k holds out every k-th view (0: none, as the
    first faithful run of issue 26)."""
    from cobgs.data.colmap import read_colmap
    from cobgs.data.sfm import run_sfm
    from cobgs.configs import SfmOptions

    sfm_dir = sfm_dir or out / "fern_sfm"
    rec_path = sfm_dir.parent / "sfm.json" if sfm_dir != out / "fern_sfm" else out / "sfm.json"
    if not (sfm_dir / "sparse" / "0").is_dir():
        if images is None:
            raise SystemExit(f"{sfm_dir}: no SfM yet; pass --images")
        t, c = time.perf_counter(), time.process_time()
        res = run_sfm(images, sfm_dir, SfmOptions(matcher="exhaustive", seed=0))
        rec = {"wall_s": time.perf_counter() - t, "cpu_s": time.process_time() - c,
               "registered": len(res.registered), "points": res.num_points3d, "peak_rss": _peak_rss()}
        rec_path.write_text(json.dumps(rec, indent=1))
        print(f"SfM: {rec['registered']} registered, {rec['points']} points, {rec['wall_s']:.1f} s", flush=True)
    return read_colmap(sfm_dir, test_every=test_every)


def _config(iterations: int, recipe: str = "3dgs", sets: tuple = ()):
    from cobgs.configs import TrainConfig

    kw = {"log_interval_its": 1000, "checkpoint_interval_its": 1000}
    if iterations:  # 0: the recipe's (a given count would override the fast recipe's own)
        kw["iterations"] = iterations
    if recipe != "3dgs":
        kw["recipe"] = recipe
    for item in sets:  # --set field=value (a TrainConfig field; value as a Python literal)
        import ast

        k, v = item.split("=", 1)
        try:
            kw[k] = ast.literal_eval(v)
        except (ValueError, SyntaxError):
            kw[k] = v
    return TrainConfig(**kw)


def cmd_scene(args) -> int:
    import torch

    from cobgs.train.optimize import train

    torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    scene = _scene(out, args.images, args.test_every, args.sfm_dir)
    ckpt_dir = out / "ckpt"
    ckpt_dir.mkdir(exist_ok=True)
    done = sorted((int(p.stem.split("_")[1]) for p in ckpt_dir.glob("ckpt_*.pt") if p.stem.split("_")[1].isdigit()))
    resume = ckpt_dir / f"ckpt_{done[-1]}.pt" if done else None
    w, h = scene.train[0].camera.width, scene.train[0].camera.height
    run_id = time.strftime("%Y-%m-%dT%H:%M:%S")
    print(f"fern: {len(scene.train)} views at {w}x{h}; resuming from {resume.name if resume else 'the start'}",
          flush=True)
    cfg = _config(args.iterations, args.recipe, tuple(args.set or ()))
    args.iterations = cfg.iterations
    (out / "config.json").write_text(json.dumps({"recipe": args.recipe, "sets": args.set or [],
                                                 "test_every": args.test_every,
                                                 "sfm_dir": str(args.sfm_dir) if args.sfm_dir else None,
                                                 "test_views": [v.name for v in scene.test]}, indent=1))
    log = (out / "train_log.jsonl").open("a")
    t_start = time.perf_counter()
    mark = [time.perf_counter(), time.process_time()]

    def callback(trainer, info):
        it = trainer.iteration
        if it % 1000:
            return
        now, cpu = time.perf_counter(), time.process_time()
        rec = {"it": it, "wall_s": now - mark[0], "cpu_s": cpu - mark[1], "gaussians": len(trainer.model),
               "loss": info["loss"], "psnr": info["psnr"], "load": os.getloadavg()[0], "run": run_id,
               "width": w, "height": h, "peak_rss": _peak_rss()}
        if info.get("resolution"):
            rec["resolution"] = info["resolution"]
        mark[0], mark[1] = now, cpu
        log.write(json.dumps(rec) + "\n")
        log.flush()
        left = (args.iterations - it) * rec["wall_s"] / 1000
        print(f"train it {it}/{args.iterations}: {rec['wall_s']:.1f} s / 1000 its, {rec['gaussians']:,} Gaussians, "
              f"loss {info['loss']:.4f}, psnr {info['psnr']:.2f}, load {rec['load']:.2f}, "
              f"ETA {left / 3600:.1f} h at this rate", flush=True)
        if ((args.budget_s and now - t_start > args.budget_s) or (args.stop_at and it >= args.stop_at)) \
                and it < args.iterations:
            trainer.save_checkpoint(ckpt_dir / f"ckpt_{it}.pt")  # train() writes it after us; same content
            raise _Budget(it)

    try:
        res = train(scene, cfg, checkpoint_dir=ckpt_dir, resume=resume, progress=False,
                    evaluate_test=bool(scene.test), callback=callback)
    except _Budget as b:
        print(f"stopped after iteration {b.args[0]} (time budget / --stop-at); run again to continue", flush=True)
        return 0
    finally:
        log.close()
    if res.eval:
        ev = {"psnr": res.eval["psnr"], "ssim": res.eval["ssim"], "per_view": res.eval["per_view"],
              "gaussians": len(res.model), "iterations": res.iterations, "peak_rss": _peak_rss()}
        (out / "eval.json").write_text(json.dumps(ev, indent=1))
        print(f"held-out ({len(scene.test)} views): PSNR {ev['psnr']:.3f} dB, SSIM {ev['ssim']:.4f}", flush=True)
    print("training complete", flush=True)
    return 0


def _run_config(out: Path) -> dict:
    """What ``bm_cost.py scene`` recorded of a run (``out/config.json``: recipe, --set switches,
    split, shared SfM); {} for a run folder without one."""
    f = out / "config.json"
    return json.loads(f.read_text()) if f.is_file() else {}


def _split_of(args) -> tuple:
    """(test_every, sfm_dir) for table6 / _one: the flags, else what the scene run recorded in
    config.json (so the refinement sees the training's split and reconstruction)."""
    cfg = _run_config(args.out)
    te = args.test_every if args.test_every is not None else int(cfg.get("test_every") or 0)
    sfm = args.sfm_dir or (Path(cfg["sfm_dir"]) if cfg.get("sfm_dir") else None)
    return te, sfm


def _object_masks(model, views):
    sys.path.insert(0, str(HERE))
    from bm_cuda import object_masks

    return object_masks(model, views)


def _load_checkpoint(scene, path: Path, iterations: int, out: Path | None = None):
    """The model and Adam moments of a checkpoint, read with the TrainConfig of the scene run
    that wrote it (its recipe and --set switches from ``out/config.json``)."""
    from cobgs.train.adam_moments import export_moments
    from cobgs.train.optimize import Trainer

    cfg = _run_config(out) if out else {}
    tr = Trainer(scene, _config(iterations if cfg.get("recipe", "3dgs") == "3dgs" else 0,
                                cfg.get("recipe", "3dgs"), tuple(cfg.get("sets") or ())))
    tr.load_checkpoint(path)
    return tr.model, export_moments(tr.optimizer)


def cmd_table6(args) -> int:
    """Masks once (PNG files), then every method in a process of its own."""
    import numpy as np
    import torch
    from PIL import Image

    out = args.out
    scene = _scene(out, None, *_split_of(args))
    ckpt = out / "ckpt" / args.checkpoint
    mask_dir = out / f"masks_{ckpt.stem}"
    if not mask_dir.is_dir():
        model, _ = _load_checkpoint(scene, ckpt, args.iterations, out)
        masks, n_obj = _object_masks(model, scene.train)
        tmp = mask_dir.with_name(mask_dir.name + ".part")
        tmp.mkdir(parents=True, exist_ok=True)
        for v, m in zip(scene.train, masks):
            Image.fromarray(m.numpy().astype(np.uint8) * 255).save(tmp / f"{v.name}.png")
        (tmp / "object.json").write_text(json.dumps({"object_gaussians": n_obj,
                                                     "coverage": float(torch.stack(masks).float().mean())}))
        tmp.rename(mask_dir)
        del model
    rows = []
    for method in args.methods.split(","):
        cmd = [sys.executable, __file__, "_one", "--out", str(out), "--checkpoint", args.checkpoint,
               "--iterations", str(args.iterations), "--method", method]
        if args.sfm_dir:
            cmd += ["--sfm-dir", str(args.sfm_dir)]
        if args.test_every is not None:
            cmd += ["--test-every", str(args.test_every)]
        print(f"{method}: running", flush=True)
        res = subprocess.run(cmd, capture_output=True, text=True)
        if res.returncode != 0:
            print(res.stdout[-2000:], res.stderr[-4000:], file=sys.stderr)
            return res.returncode
        rec = json.loads(res.stdout.strip().splitlines()[-1])
        rows.append(rec)
        print(f"{method}: prep {rec['prep_s']:.2f} s, opt {rec['opt_s']:.1f} s, seg {rec['seg_ms']:.1f} ms, "
              f"eval {rec['eval_s']:.1f} s, peak RSS {rec['peak_rss'] / 2**30:.2f} GiB, "
              f"Gaussians {rec['gaussians_start']:,} -> {rec['gaussians_end']:,}, IoU vs masks {rec['iou']:.3f}",
              flush=True)
    with (out / f"table6_{ckpt.stem}.jsonl").open("w") as f:
        for r in rows:
            f.write(json.dumps(r) + "\n")
    return 0


def cmd_one(args) -> int:
    """One method on one checkpoint (run by table6 in a process of its own)."""
    import numpy as np
    import torch
    from PIL import Image

    from cobgs.evaluate.metrics import iou
    from cobgs.refine.methods import run_method
    from cobgs.render.rasterize import rasterize
    from cobgs.refine.segment import extract

    torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))
    out = args.out
    scene = _scene(out, None, *_split_of(args))
    ckpt = out / "ckpt" / args.checkpoint
    model, moments = _load_checkpoint(scene, ckpt, args.iterations, out)
    mask_dir = out / f"masks_{ckpt.stem}"
    # prep: the masks from files, as the masks stage hands them to refine (bool at render size)
    t = time.perf_counter()
    masks = []
    for v in scene.train:
        with Image.open(mask_dir / f"{v.name}.png") as im:
            m = np.asarray(im.convert("L")) > 128
        if m.shape != (v.camera.height, v.camera.width):
            raise SystemExit(f"{mask_dir}/{v.name}.png: {m.shape} != {(v.camera.height, v.camera.width)}")
        masks.append(torch.from_numpy(m))
    prep = time.perf_counter() - t
    t, c = time.perf_counter(), time.process_time()
    res = run_method(args.method, model, scene.train, masks, scene.extent, progress=False,
                     texture_moments=moments, object_name="centre")
    opt, opt_cpu = time.perf_counter() - t, time.process_time() - c
    t = time.perf_counter()
    obj = extract(res, "foreground")
    seg = time.perf_counter() - t
    t = time.perf_counter()
    ious = []
    with torch.no_grad():
        for v, m in zip(scene.train, masks):
            cam = v.camera
            r = rasterize(obj.means, obj.quats, obj.scales, obj.opacities, torch.ones(len(obj), 1),
                          cam.viewmat, cam.K, cam.width, cam.height)
            ious.append(float(iou(r.image[..., 0] > 0.5, m)))
    ev = time.perf_counter() - t
    print(json.dumps({"method": args.method, "checkpoint": args.checkpoint, "prep_s": prep, "opt_s": opt,
                      "opt_cpu_s": opt_cpu, "seg_ms": 1000 * seg, "eval_s": ev, "peak_rss": _peak_rss(),
                      "gaussians_start": len(model), "gaussians_end": len(res.model), "object": len(obj),
                      "iou": float(np.mean(ious)), "load": os.getloadavg()[0],
                      "views": len(scene.train)}))
    return 0


def _jsonl(path: Path) -> list:
    return [json.loads(x) for x in path.read_text().splitlines() if x.strip()]


def _train_chunks(log: Path) -> list:
    """The logged 1000-iteration chunks in order; a chunk logged twice (a run stopped and
    resumed) counts once: the latest."""
    last = {r["it"]: r for r in _jsonl(log)}
    return [last[k] for k in sorted(last)]


def _paused_per_chunk(recs, pauses: Path) -> dict:
    """Seconds each logged chunk spent stopped, from ``pauses.txt`` (lines ``START END``,
    epoch seconds, written by whoever stopped the run with SIGSTOP). A chunk's interval is
    rebuilt from its run's start (the run id, local time) and the chunk walls before it, to
    within the few seconds a run takes to load its checkpoint."""
    if not pauses.is_file():
        return {}
    spans = []
    for n, line in enumerate(pauses.read_text().splitlines(), 1):
        f = line.split()
        if not f:
            continue
        try:
            a, b = float(f[0]), float(f[1])
        except (IndexError, ValueError):
            raise SystemExit(f"{pauses}:{n}: expected 'START END' (epoch seconds), got {line!r}") from None
        if b < a:
            raise SystemExit(f"{pauses}:{n}: the pause ends ({b}) before it starts ({a})")
        spans.append((a, b))
    out, end_of = {}, {}
    for r in recs:
        t0 = end_of.get(r["run"], time.mktime(time.strptime(r["run"], "%Y-%m-%dT%H:%M:%S")))
        t1 = t0 + r["wall_s"]
        end_of[r["run"]] = t1
        out[r["it"]] = sum(max(0.0, min(t1, b) - max(t0, a)) for a, b in spans)
    return out


def _scene_cost(out: Path, recs: list, paused: dict) -> list:
    """The whole scene per stage: SfM, training (measured wall without stopped time; and
    the CPU time scaled by the quietest chunks' wall / CPU ratio), COB-GS refinement and
    evaluation from the Table 6 run on the last checkpoint. ``recs`` / ``paused``: the
    training chunks and their stopped seconds (cmd_summary's)."""
    sfm = out / "sfm.json"
    t6 = sorted(out.glob("table6_ckpt_*.jsonl"), key=lambda q: int(q.stem.split("_")[-1]))
    if not (sfm.is_file() and recs and t6):
        return []
    wall = sum(r["wall_s"] - paused.get(r["it"], 0.0) for r in recs)
    cpu = sum(r["cpu_s"] for r in recs)
    quiet = [r for r in recs if r["load"] < 2.1 and paused.get(r["it"], 0.0) < 0.5]
    k = sum(r["wall_s"] for r in quiet) / sum(r["cpu_s"] for r in quiet) if quiet else float("nan")
    rows = {r["method"]: r for r in _jsonl(t6[-1])}
    if "cobgs" not in rows:
        return []
    c = rows["cobgs"]
    s_sfm = json.loads(sfm.read_text())["wall_s"]
    refine, ev = c["prep_s"] + c["opt_s"] + c["seg_ms"] / 1000, c["eval_s"]
    its = recs[-1]["it"]
    total_m = s_sfm + wall + refine + ev
    total_q = s_sfm + cpu * k + refine + ev

    def row(name, a, b):
        def sec(x):
            return f"{x:,.0f} s" if x >= 10 else f"{x:.1f} s"
        return f"| {name} | {sec(a)} ({a / total_m:.1%}) | {sec(b)} ({b / total_q:.1%}) |"

    return [f"The whole scene, per stage (training: {its:,} iterations; refinement and evaluation: COB-GS "
            f"on `{c['checkpoint']}`, V = {c['views']}). Two columns for training: the wall time as measured "
            "(without stopped time), and its CPU time times the wall / CPU ratio of the chunks that ran on a "
            f"quiet machine (load < 2.1, {len(quiet)} chunks: {k:.3f}), i.e. what the same work takes with "
            "the machine to itself.", "",
            "| stage | as measured | quiet-machine estimate |", "|---|---|---|",
            row("SfM (pycolmap)", s_sfm, s_sfm), row("3DGS training", wall, cpu * k),
            row("COB-GS refinement (prep + opt + seg)", refine, refine), row("evaluation", ev, ev),
            f"| **total** | **{total_m / 3600:.2f} h** | **{total_q / 3600:.2f} h** |", ""]


def cmd_recipes(args) -> int:
    """Issue 45's tables: each ``NAME=DIR`` scene run (recipe, switches, training time, held-out
    PSNR, peak RSS) and, where its table6 ran, the whole scene (SfM + training + COB-GS
    refinement + evaluation). Markdown on stdout (or --write)."""
    rows, notes = [], []
    for spec in args.runs:
        name, _, d = spec.partition("=")
        d = Path(d)
        recs = _train_chunks(d / "train_log.jsonl") if (d / "train_log.jsonl").is_file() else []
        if not recs:  # a mistyped folder would otherwise drop out of the table unnoticed
            raise SystemExit(f"{spec}: {d / 'train_log.jsonl'} is missing or empty (not a bm_cost.py scene run)")
        # A chunk another process disturbed, measured again alone from the checkpoint before it
        # (resuming is bit-identical: same loss, PSNR and Gaussians): remeasured.jsonl holds
        # those chunks' records (bm_cost.py scene --stop-at on a copy of the checkpoint).
        redo = {r["it"]: r for r in _jsonl(d / "remeasured.jsonl")} if (d / "remeasured.jsonl").is_file() else {}
        for i, r in enumerate(recs):
            if r["it"] in redo:
                if (redo[r["it"]]["gaussians"], redo[r["it"]]["loss"]) != (r["gaussians"], r["loss"]):
                    raise SystemExit(f"{d / 'remeasured.jsonl'}: the chunk ending at {r['it']} did not repeat the run "
                                     "(another Gaussian count or loss)")
                notes.append(f"{name}: iterations {r['it'] - 999}-{r['it']} ran beside a build (load "
                             f"{r['load']:.1f}, {r['wall_s']:.0f} s); measured again alone from the checkpoint before "
                             f"them: {redo[r['it']]['wall_s']:.0f} s (load {redo[r['it']]['load']:.1f}), the value used here.")
                recs[i] = redo[r["it"]]
        cfg = _run_config(d)
        ev = json.loads((d / "eval.json").read_text()) if (d / "eval.json").is_file() else {}
        t6 = {}
        for f in sorted(d.glob("table6_*.jsonl")):
            for r in _jsonl(f):
                if r.get("method") in ("cobgs", None):
                    t6 = r
        sfm_dir = Path(cfg["sfm_dir"]) if cfg.get("sfm_dir") else d / "fern_sfm"
        sfm = json.loads((sfm_dir.parent / "sfm.json").read_text()) if (sfm_dir.parent / "sfm.json").is_file() \
            else (json.loads((d / "sfm.json").read_text()) if (d / "sfm.json").is_file() else {})
        rows.append({"name": name, "recipe": cfg.get("recipe", "3dgs"), "sets": cfg.get("sets") or [],
                     "its": recs[-1]["it"], "done": bool(ev), "wall": sum(r["wall_s"] for r in recs),
                     "cpu": sum(r["cpu_s"] for r in recs), "gaussians": recs[-1]["gaussians"],
                     "max_gaussians": max(r["gaussians"] for r in recs),
                     "rss": max(r.get("peak_rss", 0) for r in recs), "load": statistics.mean(r["load"] for r in recs),
                     "res": recs[-1].get("resolution") or [recs[-1].get("width"), recs[-1].get("height")],
                     "psnr": ev.get("psnr"), "ssim": ev.get("ssim"), "t6": t6, "sfm_s": sfm.get("wall_s"),
                     "cpu_to": {r["it"]: r["cpu_s"] for r in recs}})
    ref = next((r for r in rows if r["name"] == args.reference), None) if args.reference else None
    extra = " CPU time vs " + args.reference + " | PSNR vs " + args.reference + " |" if ref else ""
    lines = ["| run | recipe and switches | iterations | training wall h | CPU h (all threads) | mean load | "
             "Gaussians (max) | held-out PSNR / SSIM | peak RSS |" + extra,
             "|---|---|---|---|---|---|---|---|---|" + ("---|---|" if ref else "")]
    for r in rows:
        its = f"{r['its']:,}" + ("" if r["done"] else " (stopped; no held-out eval)")
        ps = f"{r['psnr']:.3f} / {r['ssim']:.4f}" if r["psnr"] is not None else "-"
        vs = ""
        if ref:
            dp = f"{r['psnr'] - ref['psnr']:+.3f} dB" if r["psnr"] is not None and ref["psnr"] is not None else "-"
            # over the iterations both have logged (a stopped run against the same stretch of the reference)
            common = sorted(set(r["cpu_to"]) & set(ref["cpu_to"]))
            upto = common[-1] if common else 0
            c_r = sum(v for k, v in r["cpu_to"].items() if k <= upto)
            c_ref = sum(v for k, v in ref["cpu_to"].items() if k <= upto)
            span = "" if upto == ref["its"] == r["its"] else f" (its 1-{upto:,})"
            vs = f" {c_r / c_ref:.2f}x{span} | {dp} |" if c_ref else f" - | {dp} |"
        lines.append(f"| {r['name']} | {r['recipe']}{' ' + ' '.join(r['sets']) if r['sets'] else ''} | {its} | "
                     f"{r['wall'] / 3600:.2f} | {r['cpu'] / 3600:.2f} | {r['load']:.1f} | "
                     f"{r['gaussians']:,} ({r['max_gaussians']:,}) | {ps} | {r['rss'] / 2**30:.2f} GiB |" + vs)
    if notes:
        lines += [""] + [f"- {n}" for n in notes]
    whole = [r for r in rows if r["done"] and r["t6"]]
    if whole:
        lines += ["", "| run | SfM | training | COB-GS refinement (prep + optimisation + extraction) | evaluation | whole scene |",
                  "|---|---|---|---|---|---|"]
        for r in whole:
            t = r["t6"]
            ref = t["prep_s"] + t["opt_s"] + t["seg_ms"] / 1000
            tot = (r["sfm_s"] or 0) + r["wall"] + ref + t["eval_s"]
            lines.append(f"| {r['name']} | {r['sfm_s'] or 0:.0f} s | {r['wall'] / 60:.1f} min | {ref:.0f} s | "
                         f"{t['eval_s']:.0f} s | **{tot / 3600:.2f} h** |")
    text = "\n".join(lines) + "\n"
    if args.write:  # between the tag's markers of an existing document (the rest of it stays)
        from pipeline.commands import write_between

        write_between(args.write, f"<!-- bm_cost recipes {args.tag} -->", f"<!-- end bm_cost recipes {args.tag} -->",
                      "\n" + text, "--write")
    print(text)
    return 0


SUMMARY_BEGIN, SUMMARY_END = "<!-- bm_cost summary -->", "<!-- end bm_cost summary -->"


def cmd_summary(args) -> int:
    out = args.out
    lines = ["Written by `tests/benchmarks/bm_cost.py summary` from the logs of `bm_cost.py scene` and "
             "`bm_cost.py table6` (2 threads, this 2-core machine, no GPU).", ""]
    sfm = out / "sfm.json"
    if sfm.is_file():
        s = json.loads(sfm.read_text())
        lines += [f"SfM (pycolmap, exhaustive matching): {s['wall_s']:.1f} s wall, {s['registered']} registered, "
                  f"{s['points']:,} points.", ""]
    log = out / "train_log.jsonl"
    recs = _train_chunks(log) if log.is_file() else []
    paused = _paused_per_chunk(recs, out / "pauses.txt")
    if recs:
        total = sum(r["wall_s"] for r in recs)
        held = sum(paused.values())
        lines += [f"3DGS training: {len(recs)} x 1000 iterations logged, {(total - held) / 3600:.2f} h of wall time "
                  f"({sum(r['cpu_s'] for r in recs) / 3600:.2f} h CPU), over {len({r['run'] for r in recs})} run(s)"
                  + (f"; {held:.0f} s during which the run was stopped (SIGSTOP, so that benchmarks of part 3 had "
                     "the machine to themselves: `pauses.txt`) are left out of the wall time" if held else "") + ".",
                  "", "| iterations | wall s / 1000 its | CPU s (all threads) | Gaussians | PSNR (train view) | load |",
                  "|---|---|---|---|---|---|"]
        for r in recs:
            p = paused.get(r["it"], 0.0)
            wall = f"{r['wall_s'] - p:.0f}" + (f" ({r['wall_s']:.0f} with {p:.0f} s stopped)" if p >= 0.5 else "")
            lines.append(f"| {r['it'] - 999}-{r['it']} | {wall} | {r['cpu_s']:.0f} | {r['gaussians']:,} | "
                         f"{r['psnr']:.2f} | {r['load']:.2f} |")
        lines += ["", "The load column is the 1-minute load average when the chunk ended; above about 2 the "
                  "machine was also doing other work (builds, tests, benchmarks of this issue), which "
                  "slows the chunk's wall time but hardly its CPU time.", ""]
        full = 30_000
        if recs and recs[-1]["it"] < full:
            tail = recs[-3:]
            rate = sum(r["wall_s"] - paused.get(r["it"], 0.0) for r in tail) / len(tail)
            left = (full - recs[-1]["it"]) / 1000 * rate
            lines += [f"**Not measured: iterations {recs[-1]['it'] + 1}-{full}.** At the mean rate of the last "
                      f"{len(tail)} chunks ({rate:.0f} s / 1000 iterations, {recs[-1]['gaussians']:,} Gaussians) "
                      f"they would take about {left / 3600:.2f} h, for an estimated {(total - held + left) / 3600:.2f} h of "
                      "training in all (an estimate: densification, which sets the count, runs to 15k).", ""]
    for t6 in sorted(out.glob("table6_*.jsonl")):
        rows = _jsonl(t6)
        lines += [f"Paper Table 6 on a CPU, checkpoint `{rows[0]['checkpoint']}` ({rows[0]['gaussians_start']:,} "
                  f"Gaussians, V = {rows[0]['views']}, masks from PNG files):", "",
                  "| method | prep | opt | seg | eval (object masks, all views) | peak RSS | Gaussians after | "
                  "IoU vs the masks |", "|---|---|---|---|---|---|---|---|"]
        lines += [f"| {r['method']} | {r['prep_s']:.2f} s | {r['opt_s']:.1f} s | {r['seg_ms']:.1f} ms | "
                  f"{r['eval_s']:.1f} s | {r['peak_rss'] / 2**30:.2f} GiB | {r['gaussians_end']:,} | {r['iou']:.3f} |"
                  for r in rows]
        lines.append("")
    lines += _scene_cost(out, recs, paused)
    for ab in sorted(out.glob("ab_*.md")):  # bm_ab.py --write tables (part 3)
        lines += [f"Table `{ab.stem[3:]}` (`{ab.name}`, written by `bm_ab.py --write`):", ""]
        lines += ab.read_text().splitlines() + [""]
    for prof in sorted(out.glob("profile_*.txt")):  # bm_profile.py's output on a checkpoint, kept by hand
        body = [x for x in prof.read_text().splitlines() if not x.startswith("USDT:")]
        lines += [f"Where a training step's time goes on that checkpoint (`{prof.name}`: `bm_profile.py --scene fern "
                  "--ply CKPT --sfm-dir OUT/fern_sfm --threads 2 --train-steps 5 --reps 5`):", "", "```"] + body + ["```", ""]
    text = "\n".join(lines)
    print(text)
    if args.write:  # between the summary's markers of an existing document (the rest of it stays)
        from pipeline.commands import write_between

        write_between(args.write, SUMMARY_BEGIN, SUMMARY_END, "\n" + text + "\n", "--write")
    return 0


def main(argv=None) -> int:
    sys.path.insert(0, str(ROOT))
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("scene")
    s.add_argument("--images", type=Path)
    s.add_argument("--out", type=Path, required=True)
    s.add_argument("--iterations", type=int, default=0, help="0: the recipe's (3dgs: 30 000, fast: its own)")
    s.add_argument("--budget-s", type=float, default=0.0, help="stop at the first checkpoint after this long")
    s.add_argument("--stop-at", type=int, default=0, help="stop (resumably) at this iteration")
    s.add_argument("--test-every", type=int, default=0,
                   help="hold out every k-th view (0: none, as issue 26's run); held-out PSNR goes to eval.json")
    s.add_argument("--sfm-dir", type=Path, default=None, help="a shared SfM folder (default OUT/fern_sfm)")
    s.add_argument("--recipe", default="3dgs", help="TrainConfig.recipe")
    s.add_argument("--set", action="append", metavar="FIELD=VALUE", help="a TrainConfig field (repeatable)")
    t = sub.add_parser("table6")
    t.add_argument("--out", type=Path, required=True)
    t.add_argument("--checkpoint", default="ckpt_final.pt")
    t.add_argument("--iterations", type=int, default=30_000)
    t.add_argument("--sfm-dir", type=Path, default=None, help="the scene run's shared SfM (default: its config.json's)")
    t.add_argument("--test-every", type=int, default=None, help="the scene run's split (default: its config.json's)")
    t.add_argument("--methods", default=",".join(METHODS))
    o = sub.add_parser("_one")
    o.add_argument("--out", type=Path, required=True)
    o.add_argument("--checkpoint", required=True)
    o.add_argument("--iterations", type=int, default=30_000)
    o.add_argument("--sfm-dir", type=Path, default=None, help="the scene run's shared SfM (default: its config.json's)")
    o.add_argument("--test-every", type=int, default=None, help="the scene run's split (default: its config.json's)")
    o.add_argument("--method", required=True, choices=METHODS)
    rc = sub.add_parser("recipes", help="issue 45's tables over several scene runs")
    rc.add_argument("runs", nargs="+", metavar="NAME=DIR")
    rc.add_argument("--write", type=Path, help="a Markdown file: the tables replace the text between the "
                    "markers <!-- bm_cost recipes TAG --> ... <!-- end bm_cost recipes TAG --> (needs --tag)")
    rc.add_argument("--tag")
    rc.add_argument("--reference", help="a NAME: adds each run's CPU time and held-out PSNR relative to it (ablations)")
    m = sub.add_parser("summary")
    m.add_argument("--out", type=Path, required=True)
    m.add_argument("--write", type=Path, help="a Markdown file: the summary replaces the text between its "
                   "markers <!-- bm_cost summary --> ... <!-- end bm_cost summary -->")
    args = ap.parse_args(argv)
    if args.cmd == "recipes" and args.write and not args.tag:
        ap.error("recipes --write needs --tag (the markers of the section it replaces)")
    return {"scene": cmd_scene, "table6": cmd_table6, "_one": cmd_one, "summary": cmd_summary,
            "recipes": cmd_recipes}[args.cmd](args)


if __name__ == "__main__":
    raise SystemExit(main())
