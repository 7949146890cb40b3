"""Synthetic multi-object scenes with exact ground-truth masks (the embedded data set).

:func:`generate_scene` ray-casts a preset (see :data:`PRESETS`) and writes it in the
NeRF-style layout of ``docs/data_formats.md``: ``transforms.json`` (camera->world in OpenGL
axes, per-frame intrinsics, ``test_filenames``), ``images/``, ``masks/<object>/`` (a pixel
is in an object's mask when a strict majority of its subsamples see that object first),
``coverage/<object>/`` (round(255 x fraction of subsamples)), ``amodal/<object>/`` for
the held-out views (the object's whole silhouette, occluders ignored, same majority rule:
the GT of the headline protocol, docs/method.md §5) and ``scene.json``.

The output is deterministic: the same preset, seed and overrides give bit-identical files.
It is written to a temporary sibling folder and renamed into place at the end, so an
interrupted run never leaves a folder that looks finished.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np

from cobgs._atomic import build_folder_atomic
from cobgs.errors import DataError, InputError
from cobgs.data.synth.cameras import PinholeCamera, intrinsics_from_fov, opencv_to_opengl
from cobgs.data.synth.presets import BUILDERS, PRESETS, SynthPreset
from cobgs.data.synth.render import RenderedView, SynthScene, make_caster, render_view, silhouette_hits

GENERATOR = "cobgs.data.synth.scene"
FORMAT_VERSION = 1

__all__ = ["PRESETS", "SynthPreset", "build_scene", "generate_scene", "render_scene_view",
           "GENERATOR", "FORMAT_VERSION"]


def resolve_preset(preset: str | SynthPreset, **overrides) -> SynthPreset:
    """The preset named ``preset`` (or given), with non-None ``overrides`` of its fields."""
    if isinstance(preset, str):
        if preset not in PRESETS:
            raise InputError(f"unknown synthetic preset {preset!r}; expected one of {sorted(PRESETS)}")
        preset = PRESETS[preset]
    fields = {f.name for f in dataclasses.fields(SynthPreset)}
    bad = sorted(set(overrides) - fields)
    if bad:
        raise InputError(f"unknown preset field(s) {bad}; expected some of {sorted(fields)}")
    changes = {k: v for k, v in overrides.items() if v is not None}
    return dataclasses.replace(preset, **changes) if changes else preset


def build_scene(preset: str | SynthPreset, seed: int = 0, **overrides
                ) -> Tuple[SynthPreset, SynthScene, List[PinholeCamera]]:
    """The resolved preset, its scene and its cameras for ``seed`` (nothing is rendered).

    ``overrides`` replace preset fields (``width_px``, ``height_px``, ``num_views``,
    ``supersampling``, ``hfov_deg``, ``test_every``); the layout is the preset's.
    """
    p = resolve_preset(preset, **overrides)
    if p.name not in BUILDERS:
        raise InputError(f"no scene builder for preset {p.name!r}; expected one of {sorted(BUILDERS)}")
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError(f"seed must be an int >= 0, got {seed!r}")
    rng = np.random.default_rng([0x5EED, int(seed)])
    scene, poses = BUILDERS[p.name](rng, p)
    fx, fy, cx, cy = intrinsics_from_fov(p.width_px, p.height_px, p.hfov_deg)
    cams = [PinholeCamera(p.width_px, p.height_px, fx, fy, cx, cy,
                          tuple(tuple(float(v) for v in row) for row in c2w)) for c2w in poses]
    return p, scene, cams


def render_scene_view(scene: SynthScene, camera: PinholeCamera, supersampling: int) -> RenderedView:
    """Render one view (colour and per-object subsample hit counts)."""
    return render_view(scene, camera, supersampling)


# Per-process state of the worker pool (set once per worker by _init_worker).
_WORKER: dict = {}


def _init_worker(scene: SynthScene, cams: List[PinholeCamera], s: int, parent_pid: int, test_every: int) -> None:
    # A render worker must not outlive the process that started it (a SIGKILLed run would
    # leave it waiting on its task queue forever): Linux's PR_SET_PDEATHSIG ends it then.
    try:
        import ctypes
        import signal

        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL), 0, 0, 0)
    except (OSError, AttributeError):
        pass
    if os.getppid() != parent_pid:
        os._exit(1)
    _WORKER.update(scene=scene, cams=cams, s=s, caster=make_caster(scene), test_every=test_every)


def _render_one(scene: SynthScene, cam: PinholeCamera, s: int, caster, held_out: bool):
    view = render_view(scene, cam, s, caster=caster)
    return view, (silhouette_hits(scene, cam, s, caster=caster) if held_out else None)


def _render_index(i: int):
    w = _WORKER
    return _render_one(w["scene"], w["cams"][i], w["s"], w["caster"], i % w["test_every"] == 0)


def _render_all(scene: SynthScene, cams: List[PinholeCamera], s: int, progress: bool, workers: int,
                test_every: int):
    """Yield (view, silhouette hits of the held-out views, else None) in order; views are
    independent, so ``workers`` processes render them in parallel with identical results."""
    from tqdm import tqdm

    bar = tqdm(total=len(cams), desc="synth: rendering views", unit="view", disable=not progress)
    try:
        if workers <= 1:
            caster = make_caster(scene)
            for i, cam in enumerate(cams):
                yield _render_one(scene, cam, s, caster, i % test_every == 0)
                bar.update()
            return
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        methods = mp.get_all_start_methods()
        ctx = mp.get_context("fork" if "fork" in methods else "spawn")
        pool = ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init_worker,
                                   initargs=(scene, cams, s, os.getpid(), test_every))
        try:
            for view in pool.map(_render_index, range(len(cams))):
                yield view
                bar.update()
        finally:
            # On an error or Ctrl-C, drop the views not started yet instead of waiting.
            pool.shutdown(wait=True, cancel_futures=True)
    finally:
        bar.close()


def _frame_json(cam: PinholeCamera, file_path: str) -> dict:
    gl = opencv_to_opengl(cam.c2w_array)
    return {"file_path": file_path,
            "transform_matrix": [[float(v) for v in row] for row in gl],
            "fl_x": cam.fx, "fl_y": cam.fy, "cx": cam.cx, "cy": cam.cy,
            "w": cam.width, "h": cam.height}


def _write_png(path: Path, array: np.ndarray) -> None:
    import cv2

    img = array[:, :, ::-1] if array.ndim == 3 else array  # OpenCV writes BGR
    if not cv2.imwrite(str(path), np.ascontiguousarray(img)):
        raise DataError("could not write PNG", path)


def is_synthetic_scene(folder: os.PathLike | str) -> bool:
    """Whether ``folder`` is a scene :func:`generate_scene` wrote (its ``scene.json`` names
    this generator)."""
    f = Path(folder) / "scene.json"
    try:
        meta = json.loads(f.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(meta, dict) and meta.get("generator") == GENERATOR


def check_replaceable_scene(out: Path) -> None:
    """``overwrite`` replaces only a scene this generator wrote: never a plain file, a
    symlink or a folder of anything else (a user's folder given by mistake).

    Raises:
        InputError: naming the destination and what it holds.
    """
    if out.is_symlink() or not out.is_dir():
        raise InputError(f"--overwrite replaces only a scene folder `cobgs synth` wrote; {out} is "
                         f"{'a symlink' if out.is_symlink() else 'a file'}: refusing to replace it")
    if not is_synthetic_scene(out):
        have = sorted(p.name for p in out.iterdir())[:6]
        raise InputError(f"--overwrite replaces only a scene folder `cobgs synth` wrote (its scene.json "
                         f"names {GENERATOR!r}); {out} holds {have}: refusing to delete it (choose another --out)")


def generate_scene(out_dir: os.PathLike | str, preset: str | SynthPreset = "demo", seed: int = 0,
                   *, overwrite: bool = False, progress: bool = True,
                   width_px: Optional[int] = None, height_px: Optional[int] = None,
                   num_views: Optional[int] = None, supersampling: Optional[int] = None,
                   workers: int = 1) -> Path:
    """Render a synthetic scene and write it to ``out_dir``.

    Args:
        out_dir: destination folder; must not exist (or be empty) unless ``overwrite``.
        preset: "demo", "forward", "orbit" or a :class:`SynthPreset` with one of those names.
        seed: changes colours, texture lattices, box yaws and camera jitter.
        overwrite: replace an existing ``out_dir`` that is a scene this function wrote
            (anything else is refused: :func:`check_replaceable_scene`); the new scene is
            built beside it and swapped in whole.
        progress: show a tqdm bar.
        width_px, height_px, num_views, supersampling: override the preset's values.
        workers: processes rendering views in parallel (0: one per CPU core); the output
            does not depend on it.
    Returns:
        ``out_dir`` as a Path.
    """
    out = Path(out_dir)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        if not overwrite:
            raise InputError(f"output folder {out} exists and is not empty (pass overwrite=True "
                             "or --overwrite to replace it)")
        check_replaceable_scene(out)
    if not isinstance(workers, int) or workers < 0:
        raise InputError(f"workers must be an int >= 0, got {workers!r}")
    workers = workers or (os.cpu_count() or 1)
    p, scene, cams = build_scene(preset, seed, width_px=width_px, height_px=height_px,
                                 num_views=num_views, supersampling=supersampling)
    return build_folder_atomic(out, lambda tmp: _write(tmp, p, scene, cams, seed, progress, workers))


def _write(root: Path, p: SynthPreset, scene: SynthScene, cams: List[PinholeCamera], seed: int,
           progress: bool, workers: int) -> None:
    names = [o.name for o in scene.objects]
    (root / "images").mkdir()
    for sub in ("masks", "coverage", "amodal"):
        for n in names:
            (root / sub / n).mkdir(parents=True)
    frames, test = [], []
    s = p.supersampling
    for i, (view, silhouettes) in enumerate(_render_all(scene, cams, s, progress, workers, p.test_every)):
        stem = f"{i:04d}"
        rel = f"images/{stem}.png"
        _write_png(root / rel, view.rgb)
        for k, n in enumerate(names):
            hits = view.hits[k].astype(np.int64)
            # Strict majority of subsamples: a pixel split evenly between two surfaces
            # belongs to neither mask.
            _write_png(root / "masks" / n / f"{stem}.png",
                       np.where(2 * hits > view.subsamples, 255, 0).astype(np.uint8))
            cov = np.rint(255.0 * hits / view.subsamples).astype(np.uint8)
            _write_png(root / "coverage" / n / f"{stem}.png", cov)
            if silhouettes is not None:
                _write_png(root / "amodal" / n / f"{stem}.png",
                           np.where(2 * silhouettes[k].astype(np.int64) > view.subsamples, 255, 0).astype(np.uint8))
        frames.append(_frame_json(cams[i], rel))
        if i % p.test_every == 0:
            test.append(rel)
    c0 = cams[0]
    transforms = {"camera_model": "PINHOLE", "fl_x": c0.fx, "fl_y": c0.fy, "cx": c0.cx,
                  "cy": c0.cy, "w": c0.width, "h": c0.height, "frames": frames,
                  "test_filenames": test}
    _dump(root / "transforms.json", transforms)
    light = np.asarray(scene.light_dir, dtype=np.float64)
    meta = {
        "generator": GENERATOR, "version": FORMAT_VERSION, "preset": p.name, "seed": int(seed),
        "trajectory": p.trajectory, "image_size": [p.width_px, p.height_px],
        "supersampling": s, "subsamples_per_pixel": s * s, "num_views": len(cams),
        "test_every": p.test_every, "hfov_deg": p.hfov_deg, "world_up": [0.0, 0.0, 1.0],
        "mask_rule": "2 * hits > subsamples_per_pixel",
        "amodal_masks": "amodal/<object>/<view>.png, held-out views: the whole silhouette, occluders ignored",
        "objects": [o.to_json() for o in scene.objects],
        "background": [b.to_json() for b in scene.background],
        "light": {"direction": (light / np.linalg.norm(light)).tolist(), "ambient": scene.ambient,
                  "sky": list(scene.sky)},
    }
    # scene.json last: its presence marks a complete scene even inside the temp folder.
    _dump(root / "scene.json", meta)


def _dump(path: Path, obj: Dict) -> None:
    with open(path, "w", encoding="utf-8") as f:
        json.dump(obj, f, indent=1)
        f.write("\n")
