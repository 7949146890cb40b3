"""Stage ``train``: the baseline 3DGS scene (cobgs.train.optimize) that every method refines.

Params are :class:`cobgs.configs.TrainConfig` itself (``--set train.iterations=3000``).
Output ``scene``: ``scene.ply`` (standard 3DGS layout), ``adam_moments.pt`` (the
optimizer's final Adam moments, which COB-GS's texture stages continue from, as the
released code continues its 3DGS checkpoint; :mod:`cobgs.train.adam_moments`), ``train.json`` (config, resolved
schedule, loss / PSNR history, held-out PSNR / SSIM per view, Gaussian count, timings) and
``renders/<view>.png`` (8-bit renders of the held-out views: the vanilla side of the
texture comparison).

With the scene's ``trained`` attribute the stage imports that scene instead of training
(:mod:`cobgs.data.trained3dgs`: an original-3DGS output folder, with its checkpoint's Adam
state when present, or any standard 3DGS PLY), checked against the data; train.json's
``imported`` says what was read.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

from cobgs.configs import Files, TrainConfig, key_without_later
from pipeline import Resources, Stage

from ._common import load_scene, to_device, torch_device, write_json, write_png


def _run(ctx, inputs):
    import torch

    from cobgs.train.adam_moments import MOMENTS_FILE, save_moments
    from cobgs.gaussians.ply import save_ply
    from cobgs.render.image import render_image
    from cobgs.train.optimize import train

    cfg: TrainConfig = ctx.params
    scene = to_device(load_scene(inputs["dataset"], inputs["poses"]), ctx.device)
    dev = torch_device(ctx.device)
    trained = getattr(ctx.item.attrs.get("scene"), "trained", None)
    if trained is not None:
        return _import_trained(ctx, cfg, scene, dev, Path(trained))
    ctx.log.info("training %d iterations on %d views (%d held out), %s", cfg.iterations, len(scene.train),
                 len(scene.test), ctx.device)
    bar = ctx.progress(total=cfg.iterations, desc=f"train[{ctx.item.label}]")
    last = {"n": 0}

    def callback(trainer, info):
        bar.update(1)
        if trainer.iteration % max(1, cfg.log_interval_its) == 0:
            last["n"] = len(trainer.model)
            if hasattr(bar, "set_postfix"):
                extra = {}
                if cfg.resolution_schedule:  # the rendered size this iteration
                    extra["res"] = "x".join(str(v) for v in info["resolution"])
                if trainer.budget:
                    extra["budget"] = trainer.budget
                bar.set_postfix(loss=f"{info['loss']:.4f}", psnr=f"{info['psnr']:.2f}", gaussians=last["n"], **extra)

    t0 = time.perf_counter()
    res = train(scene, cfg, progress=False, callback=callback)
    if hasattr(bar, "close"):
        bar.close()
    wall = time.perf_counter() - t0
    model = res.model
    save_ply(ctx.out_dir / Files.SCENE_PLY, model.to(torch.device("cpu")) if dev.type != "cpu" else model)
    save_moments(ctx.out_dir / MOMENTS_FILE, res.adam_moments, len(model))
    bg = cfg.background if cfg.background is not None else scene.background
    for v in scene.test:
        write_png(ctx.out_dir / Files.RENDERS / f"{v.name}.png",
                  render_image(model, v.camera, bg, backend=cfg.backend).clamp(0, 1).cpu().numpy())
    ev = res.eval or {}
    write_json(ctx.out_dir / Files.TRAIN, {
        # (the later switches left out at their earlier values: a 3dgs run writes the same bytes as before them)
        "config": key_without_later(TrainConfig, dataclasses.asdict(cfg)),
        "schedule": dataclasses.asdict(cfg.schedule()),
        "iterations": res.iterations,
        "num_gaussians": len(model),
        "train_views": [v.name for v in scene.train],
        "test_views": [v.name for v in scene.test],
        "extent": scene.extent,
        "background": list(bg),
        "eval": ev,
        "history": res.history,
        "initial_points": (int(len(scene.points)) if scene.points is not None and len(scene.points)
                           else f"random box ({cfg.random_init_points})"),
        **({"gaussian_budget": res.budget} if res.budget else {}),  # (TrainConfig.budget_for; none: left out)
        **({"stopped_at_plateau": res.stopped_at} if res.stopped_at else {}),  # (TrainConfig.stop_at_plateau)
    })  # timings are in the manifest (ctx.note): a recompute gives the same bytes
    ctx.log.info("trained: %d Gaussians, held-out PSNR %s dB, %.1f s (%.3f s/it)", len(model),
                 f"{ev['psnr']:.2f}" if ev else "n/a", wall, res.s_per_it)
    ctx.note(num_gaussians=len(model), iterations=res.iterations, psnr=ev.get("psnr"), ssim=ev.get("ssim"),
             s_per_it=res.s_per_it, train_s=wall, train_peak_rss_bytes=res.peak_rss_bytes,
             train_views=len(scene.train), test_views=len(scene.test))
    return {"scene": ctx.out_dir}


def _import_trained(ctx, cfg, scene, dev, path: Path):
    """The scene's ``trained`` 3DGS instead of training one: read, checked against the data,
    written as this stage's artifacts (scene.ply, its Adam moments when a checkpoint holds
    them, train.json saying where it came from, the held-out renders)."""
    from cobgs.train.adam_moments import MOMENTS_FILE, save_moments
    from cobgs.gaussians.ply import save_ply
    from cobgs.render.image import render_image
    from cobgs.train.optimize import evaluate
    from cobgs.data.trained3dgs import check_against_scene, read_trained

    t0 = time.perf_counter()
    attrs = ctx.item.attrs["scene"]
    imp = read_trained(path, attrs.trained_iteration)
    checks = check_against_scene(imp, scene)
    if checks.get("warning"):
        ctx.warn(f"trained scene {path}: {checks['warning']}")
    model = imp.model
    save_ply(ctx.out_dir / Files.SCENE_PLY, model)
    if imp.moments is not None:
        save_moments(ctx.out_dir / MOMENTS_FILE, imp.moments, len(model))
    bg = cfg.background if cfg.background is not None else scene.background
    model = model.to(dev) if dev.type != "cpu" else model
    for v in scene.test:
        write_png(ctx.out_dir / Files.RENDERS / f"{v.name}.png",
                  render_image(model, v.camera, bg, backend=cfg.backend).clamp(0, 1).cpu().numpy())
    ev = evaluate(model, scene.test, bg, backend=cfg.backend) if scene.test else {}
    wall = time.perf_counter() - t0
    write_json(ctx.out_dir / Files.TRAIN, {
        "imported": imp.source, "checks": checks, "notes": imp.notes,
        "config": dataclasses.asdict(cfg), "iterations": int(imp.source.get("iteration", 0)),
        "num_gaussians": len(model),
        "train_views": [v.name for v in scene.train], "test_views": [v.name for v in scene.test],
        "extent": scene.extent, "background": list(bg), "eval": ev, "history": [],
    })
    ctx.log.info("imported %s (%s): %d Gaussians, %.0f%% inside the training views, held-out "
                 "PSNR %s dB; %s", path, imp.source["kind"], len(model),
                 100 * checks["visible_fraction"], f"{ev['psnr']:.2f}" if ev else "n/a",
                 "; ".join(imp.notes) or "no notes")
    ctx.note(imported=imp.source["kind"], train_s=wall, num_gaussians=len(model), psnr=ev.get("psnr"),
             ssim=ev.get("ssim"), train_views=len(scene.train), test_views=len(scene.test),
             moments=imp.moments is not None)
    return {"scene": ctx.out_dir}


def _key_params(params: TrainConfig, full: dict) -> dict:
    """Every param, except those added later while they hold their earlier value (the 3dgs
    recipe's switches): a cache written before they existed is reused."""
    return key_without_later(TrainConfig, full)


STAGE = Stage(
    name="train", version=4, run=_run, inputs=("dataset", "poses"), outputs=("scene",), params=TrainConfig,
    key_params=_key_params,
    level=("scene",), uses_device=True, resources=Resources(cpus=2),
    description="baseline 3DGS optimisation (scene.ply, held-out renders and PSNR)",
)
