"""Entry points the pipeline's masks stage calls.

* :func:`generate_masks` — text prompt, two-stage (Grounding DINO + SAM2 video);
* :func:`generate_masks_from_scribbles` — NVOS scribbles -> points -> SAM2 video;
* :func:`generate_masks_from_points` — points and/or a box on one frame -> SAM2 video;
* :func:`generate_masks_from_clicks` — clicks on one or more frames -> SAM2 video (the
  ``points`` mask source; :mod:`cobgs.masks.clicks` reads the click files).

Each writes ``<out_dir>/<image stem>.png`` (or ``<name>.png`` with ``names``) (8-bit 0/255, each image's own size) for every
frame, then a JSON log (default ``<out_dir>.json`` beside the folder), atomically.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Union

import numpy as np

from cobgs.errors import InputError, ModelError

from cobgs.masks.encoder_cache import EncoderCache
from cobgs.masks.manifest import ModelsNotConfiguredError, load_manifest
from cobgs.configs import ScribbleConfig, TwoStageConfig
from cobgs.masks.scribbles import scribble_points
from cobgs.masks.session import SessionOptions
from cobgs.masks.two_stage import run_two_stage
from cobgs.masks.video import VideoPredictor
from cobgs.masks.writer import write_json, write_mask_png

log = logging.getLogger("cobgs.masks")
PathLike = Union[str, os.PathLike]
LOG_VERSION = 1


@dataclass(frozen=True)
class MaskGenerationResult:
    """Where the masks went and what happened per frame.

    Attributes:
        out_dir: folder of ``<stem>.png`` masks.
        log_path: the JSON log.
        sources: per frame, in input order: "prompt", "stage1", "stage2_prompt",
            "stage2", "propagated" or "empty".
        empty: stems whose mask has no foreground pixel.
    """

    out_dir: Path
    log_path: Path
    sources: List[str]
    empty: List[str]


def _paths(image_paths: Sequence[PathLike]) -> List[Path]:
    paths = [Path(p) for p in image_paths]
    if not paths:
        raise InputError("image_paths is empty")
    stems = [p.stem for p in paths]
    dup = sorted({s for s in stems if stems.count(s) > 1})
    if dup:
        raise InputError(f"image stems must be unique (masks are named by stem); repeated: {dup}")
    missing = [str(p) for p in paths if not p.is_file()]
    if missing:
        raise InputError(f"image file(s) not found: {missing[:5]}")
    return paths


def _sam2(models_dir: PathLike, options: Optional[SessionOptions]):
    from cobgs.masks.sam2_models import Sam2Models

    manifest = load_manifest(models_dir)
    if manifest.sam2 is None:
        raise ModelsNotConfiguredError("the manifest has no 'sam2' model", manifest.root)
    return manifest, Sam2Models(manifest.sam2, options)


def _names(paths: List[Path], names: Optional[Sequence[str]]) -> List[str]:
    """The masks' file stems: ``names`` (one per image, unique, plain file names) or the
    images' stems."""
    if names is None:
        return [p.stem for p in paths]
    names = [str(n) for n in names]
    if len(names) != len(paths):
        raise InputError(f"names must give one name per image: {len(names)} names for {len(paths)} images")
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError(f"mask names must be unique; repeated: {dup}")
    bad = [n for n in names if not n or n in (".", "..") or "/" in n or "\\" in n or "\0" in n]
    if bad:
        raise InputError(f"mask names must be plain file names, got {bad[:3]}")
    return names


def _finish(paths, masks, sources, out_dir, log_path, log_data, models, cache, t0, stems=None):
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    stems = [p.stem for p in paths] if stems is None else list(stems)
    for stem, m in zip(stems, masks):
        write_mask_png(out_dir / f"{stem}.png", m)
    frames = [
        {"index": i, "stem": stem, "image": p.name, "source": s, "empty": s == "empty",
         "area_px": int(np.count_nonzero(m)), "size_hw": list(m.shape)}
        for i, (p, stem, m, s) in enumerate(zip(paths, stems, masks, sources))
    ]
    counts: Dict[str, int] = {}
    for s in sources:
        counts[s] = counts.get(s, 0) + 1
    log_data.update({
        "format": "cobgs-mask-generation", "version": LOG_VERSION,
        "frames": frames,
        "summary": counts,
        "graph_calls": models.call_counts(),
        "encoder_runs_max_per_frame": cache.max_encodes_per_frame(),
        "encoder_cache_hits": cache.hits,
        "providers": {k: s.providers for k, s in models.sessions.items()},
        "seconds": round(time.perf_counter() - t0, 3),
    })
    log_path = Path(log_path) if log_path is not None else out_dir.with_name(out_dir.name + ".json")
    write_json(log_path, log_data)  # last: its presence means the masks are complete
    empty = [f["stem"] for f in frames if f["empty"]]
    if empty:
        log.warning("%d of %d frames have an empty mask: %s", len(empty), len(frames), empty[:10])
    return MaskGenerationResult(out_dir, log_path, list(sources), empty)


def generate_masks(
    image_paths: Sequence[PathLike],
    prompt: str,
    models_dir: PathLike,
    out_dir: PathLike,
    *,
    config: TwoStageConfig = TwoStageConfig(),
    names: Optional[Sequence[str]] = None,
    log_path: Optional[PathLike] = None,
    options: Optional[SessionOptions] = None,
) -> MaskGenerationResult:
    """Two-stage text-prompted masks for an ordered image sequence.

    Args:
        image_paths: the training images in sequence order (the masks take their size
            and stem).
        prompt: the object's text, e.g. "red apple".
        models_dir: folder with ``manifest.json`` and both exports.
        out_dir: the object's mask folder, e.g. ``<scene>/masks/<object>``.
        config: thresholds and the prompt frame index.
        names: the masks' file stems, one per image (default: the images' stems).

    Raises:
        ModelsNotConfiguredError: no model folder / manifest, or a model is missing.
        ModelError: an export breaks the contract (named file, tensor, expected, found).
        NoDetectionError: nothing detected on the prompt frame.
    """
    from cobgs.masks.gdino import GroundingDino

    t0 = time.perf_counter()
    paths = _paths(image_paths)
    stems = _names(paths, names)
    manifest, models = _sam2(models_dir, options)
    if manifest.gdino is None:
        raise ModelsNotConfiguredError(
            "text prompts need Grounding DINO, but the manifest has no 'groundingdino' model "
            "(run `cobgs export-onnx gdino ...`)", manifest.root)
    models.require_video()
    detector = GroundingDino(manifest.gdino, options)
    cache = EncoderCache(models, paths)
    detector.check_frames(cache.size_hw(i) for i in range(len(cache)))  # before any encoding
    try:
        predictor = VideoPredictor(models, cache)
        result = run_two_stage(detector, predictor, prompt, config)
        data = dict(result.log)
        data["detector_calls"] = detector.session.stats.calls
        data["images"] = [str(p) for p in paths]
        return _finish(paths, result.masks, result.source, out_dir, log_path, data, models,
                       cache, t0, stems)
    finally:
        cache.close()


def generate_masks_from_points(
    image_paths: Sequence[PathLike],
    frame: int,
    models_dir: PathLike,
    out_dir: PathLike,
    *,
    points: Optional[np.ndarray] = None,
    labels: Optional[np.ndarray] = None,
    box: Optional[Sequence[float]] = None,
    names: Optional[Sequence[str]] = None,
    log_path: Optional[PathLike] = None,
    options: Optional[SessionOptions] = None,
    extra_log: Optional[dict] = None,
) -> MaskGenerationResult:
    """Prompt ``frame`` with points (x, y in that image's pixels; labels 1/0) and/or a
    box, propagate forward and backward to every frame, and write the masks.

    With a single image an image-only SAM2 export is enough; longer sequences need the
    video export (a clear :class:`~cobgs.errors.ModelError` otherwise). ``names``: the
    masks' file stems, one per image (default: the images' stems; e.g. the view names
    ``IMG_4026`` of LLFF's ``images_4/image000.png``).
    """
    paths = _paths(image_paths)
    if not 0 <= frame < len(paths):
        raise InputError(f"frame must be in [0, {len(paths)}), got {frame}")
    return generate_masks_from_clicks(paths, [FramePrompt(frame, points, labels, box)], models_dir, out_dir,
                                      names=names, log_path=log_path, options=options, extra_log=extra_log)


@dataclass(frozen=True)
class FramePrompt:
    """A prompt on one frame: points (x, y in that image's pixels) with labels 1 / 0,
    and/or a box (x0, y0, x1, y1)."""

    frame: int
    points: Optional[np.ndarray] = None
    labels: Optional[np.ndarray] = None
    box: Optional[Sequence[float]] = None


def generate_masks_from_clicks(
    image_paths: Sequence[PathLike],
    prompts: Sequence[FramePrompt],
    models_dir: PathLike,
    out_dir: PathLike,
    *,
    names: Optional[Sequence[str]] = None,
    log_path: Optional[PathLike] = None,
    options: Optional[SessionOptions] = None,
    extra_log: Optional[dict] = None,
) -> MaskGenerationResult:
    """Prompt one object on one or more frames, propagate with the SAM2 video predictor,
    and write the masks.

    Every prompted frame becomes a conditioning frame (every tracked frame attends to all
    of them); tracking runs forward from the first prompted frame to the last image, then
    backward from the first prompted frame to the first image, as SAM2's
    ``propagate_in_video`` starts both directions at the earliest conditioning frame.

    Args:
        image_paths: the images in sequence order.
        prompts: at most one per frame.
        names: the masks' file stems, one per image (default: the images' stems).
    """
    t0 = time.perf_counter()
    paths = _paths(image_paths)
    stems = _names(paths, names)
    if not prompts:
        raise InputError("no prompt: give at least one frame with points or a box")
    frames = [p.frame for p in prompts]
    for f in frames:
        if not 0 <= f < len(paths):
            raise InputError(f"prompt frame must be in [0, {len(paths)}), got {f}")
    if len(set(frames)) != len(frames):
        raise InputError(f"more than one prompt for frame(s) {sorted({f for f in frames if frames.count(f) > 1})}")
    _, models = _sam2(models_dir, options)
    if len(paths) > 1:
        models.require_video()
    cache = EncoderCache(models, paths)
    try:
        predictor = VideoPredictor(models, cache)
        masks: List[Optional[np.ndarray]] = [None] * len(paths)
        for pr in sorted(prompts, key=lambda q: q.frame):
            masks[pr.frame] = predictor.add_prompt(pr.frame, 1, points=pr.points, labels=pr.labels, box=pr.box)
            if not masks[pr.frame].any():
                log.warning("SAM2 returned an empty mask for the prompt on frame %d (%s): "
                            "propagation from it will find nothing", pr.frame, paths[pr.frame].name)
        first = min(frames)
        if len(paths) > 1:
            for f, per_obj in predictor.propagate(first, len(paths) - 1):
                masks[f] = per_obj[1]
            if first > 0:
                for f, per_obj in predictor.propagate(first, 0, reverse=True):
                    masks[f] = per_obj[1]
        prompted = set(frames)
        sources = ["prompt" if i in prompted else "propagated" for i in range(len(paths))]
        sources = [s if m.any() else "empty" for s, m in zip(sources, masks)]

        def _json(pr: FramePrompt) -> dict:
            return {"frame": pr.frame, "stem": stems[pr.frame],
                    "points": None if pr.points is None else np.asarray(pr.points).round(3).tolist(),
                    "labels": None if pr.labels is None else np.asarray(pr.labels).astype(int).tolist(),
                    "box_xyxy": None if pr.box is None else [float(v) for v in pr.box]}

        data = {"prompt_frame": first, "prompts": [_json(pr) for pr in sorted(prompts, key=lambda q: q.frame)],
                "images": [str(p) for p in paths], **(extra_log or {})}
        if len(prompts) == 1:  # the single-frame log's keys, as before
            data.update({k: v for k, v in data["prompts"][0].items() if k in ("points", "labels", "box_xyxy")})
        return _finish(paths, masks, sources, out_dir, log_path, data, models, cache, t0, stems)
    finally:
        cache.close()


def generate_masks_from_scribbles(
    image_paths: Sequence[PathLike],
    reference_frame: int,
    positive_scribbles: Sequence[PathLike],
    negative_scribbles: Sequence[PathLike],
    models_dir: PathLike,
    out_dir: PathLike,
    *,
    config: ScribbleConfig = ScribbleConfig(),
    log_path: Optional[PathLike] = None,
    names: Optional[Sequence[str]] = None,
    options: Optional[SessionOptions] = None,
) -> MaskGenerationResult:
    """NVOS protocol: scribbles on the reference view -> sampled points -> SAM2 on that
    view -> propagation to all views (docs/method.md §5)."""
    paths = _paths(image_paths)
    if not 0 <= reference_frame < len(paths):
        raise InputError(f"reference_frame must be in [0, {len(paths)}), got {reference_frame}")
    from cobgs.masks.images import image_size

    pts, labs = scribble_points(positive_scribbles, negative_scribbles,
                                image_size(paths[reference_frame]), config)
    extra = {"scribbles": {"positive": [str(p) for p in positive_scribbles],
                           "negative": [str(p) for p in negative_scribbles],
                           "config": asdict(config),
                           "num_positive": int((labs == 1).sum()),
                           "num_negative": int((labs == 0).sum())}}
    return generate_masks_from_points(paths, reference_frame, models_dir, out_dir, points=pts,
                                      labels=labs, names=names, log_path=log_path, options=options,
                                      extra_log=extra)


__all__ = [
    "FramePrompt", "MaskGenerationResult", "ModelError", "ModelsNotConfiguredError", "generate_masks",
    "generate_masks_from_clicks", "generate_masks_from_points", "generate_masks_from_scribbles",
]
