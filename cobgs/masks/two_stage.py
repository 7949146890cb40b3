"""Two-stage mask generation from a text prompt (paper Alg. 1), as the authors ran it.

The defaults follow the authors' script (Grounded-SAM-2's video predictor, their stage-2
loop); every place where this module can differ is a named :class:`TwoStageConfig` option.

Stage 1: Grounding DINO on the prompt frame at box threshold 0.3 / text threshold 0.45;
boxes with confidence >= 0.7 x the best become box prompts, one tracked object each
(SAM2's video predictor takes one box per object), object ids in the detector's query
order (``detection_order``); propagate forward, and backward when the prompt frame is not
the first. A frame is empty when the first object's mask has no foreground pixel
(``empty_rule``; "union": when no object's has).

Stage 2: scanning forward, each still-empty frame is detected again at box threshold
max(0.6, 0.85 x best stage-1 confidence) and text threshold max(0.65, 0.85 x best); when
boxes are found they prompt that frame (paired with the objects in id order) and the
objects are propagated forward to the end of the run of consecutive empty frames holding
it (FindMaxSub), and backward to the run's start only when ``stage2_backward``.

Every frame was tracked in stage 1, so a stage-2 box is a *correction* of a tracked frame
(``stage2_reprompt="correct"``, SAM2's own rule: decoded with memory and the frame's
previous mask, kept as a tracked frame; see :mod:`cobgs.masks.video`); "condition" makes
it a new conditioning frame instead.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field
from typing import Dict, List, Optional

import numpy as np

from cobgs.configs import TwoStageConfig
from cobgs.errors import CobgsError, InputError

from cobgs.masks.gdino import Detection, GroundingDino
from cobgs.masks.video import VideoPredictor


log = logging.getLogger("cobgs.masks")


class NoDetectionError(CobgsError):
    """Grounding DINO found nothing on the prompt frame: tracking would silently fail."""


@dataclass
class TwoStageResult:
    """Per-frame outcome. ``source[i]`` is one of "prompt", "stage1", "stage2_prompt",
    "stage2", "empty"; ``masks[i]`` is bool [H_i, W_i]."""

    masks: List[np.ndarray]
    source: List[str]
    log: dict = field(default_factory=dict)


def _det(d: Detection) -> dict:
    return {"box_xyxy": [round(v, 3) for v in d.box_xyxy], "confidence": round(d.confidence, 6),
            "phrase": d.phrase}


def run_two_stage(
    detector: GroundingDino,
    predictor: VideoPredictor,
    prompt: str,
    config: TwoStageConfig = TwoStageConfig(),
) -> TwoStageResult:
    """Alg. 1 over the predictor's frame sequence; see the module docstring."""
    n = predictor.num_frames
    p = config.prompt_frame
    if not 0 <= p < n:
        raise InputError(f"prompt_frame must be in [0, {n}), got {p}")
    cache = predictor.cache
    dets = detector.detect(cache.rgb(p), prompt, config.box_threshold, config.text_threshold,
                           order=config.detection_order)
    if not dets:
        raise NoDetectionError(
            f"Grounding DINO found no '{prompt}' on the prompt frame {p} at box threshold "
            f"{config.box_threshold}; choose another prompt frame or prompt text"
        )
    best = max(d.confidence for d in dets)
    kept = [d for d in dets if d.confidence >= config.keep_ratio_of_best * best]
    obj_ids = list(range(1, len(kept) + 1))
    source = ["empty"] * n
    prompt_masks = [predictor.add_prompt(p, obj, box=d.box_xyxy)
                    for obj, d in zip(obj_ids, kept)]
    prompt_empty = not any(m.any() for m in prompt_masks)
    if prompt_empty:
        # every later frame depends on this one: say so instead of failing silently
        log.warning("SAM2 returned an empty mask for the detected box(es) on the prompt frame "
                    "%d: tracking will find nothing (an FP16 export, or preprocessing that "
                    "does not match the export, can cause this)", p)
    masks: List[Optional[np.ndarray]] = [None] * n

    def record(frame: int, per_obj: Dict[int, np.ndarray], label: str) -> None:
        masks[frame] = np.logical_or.reduce(list(per_obj.values()))  # written: the union
        judged = per_obj[obj_ids[0]] if config.empty_rule == "first_object" else masks[frame]
        source[frame] = label if judged.any() else "empty"

    for frame, per_obj in predictor.propagate(p, n - 1):
        record(frame, per_obj, "prompt" if frame == p else "stage1")
    if p > 0:
        for frame, per_obj in predictor.propagate(p, 0, reverse=True):
            if frame != p:
                record(frame, per_obj, "stage1")
    stage1_empty = [i for i in range(n) if source[i] == "empty"]

    high = max(config.stage2_box_threshold_min, config.stage2_ratio_of_best * best)
    text_high = max(config.stage2_text_threshold_min, config.stage2_ratio_of_best * best)
    attempts = []
    f = 0
    while config.run_stage2 and f < n:
        if source[f] != "empty":
            f += 1
            continue
        found = detector.detect(cache.rgb(f), prompt, high, text_high, order=config.detection_order)
        attempt = {"frame": f, "detections": [_det(d) for d in found]}
        attempts.append(attempt)
        if not found:
            f += 1
            continue
        a, b = f, f  # FindMaxSub: the maximal run of consecutive empty frames around f
        while a > 0 and source[a - 1] == "empty":
            a -= 1
        while b < n - 1 and source[b + 1] == "empty":
            b += 1
        attempt["run"] = [a, b]
        for obj, d in zip(obj_ids, found):
            predictor.add_prompt(f, obj, box=d.box_xyxy, on_tracked=config.stage2_reprompt)
        for frame, per_obj in predictor.propagate(f, b):
            record(frame, per_obj, "stage2_prompt" if frame == f else "stage2")
        if config.stage2_backward and a < f:
            for frame, per_obj in predictor.propagate(f, a, reverse=True):
                if frame != f:
                    record(frame, per_obj, "stage2")
        f += 1

    info = {
        "prompt": prompt,
        "prompt_frame": p,
        "config": asdict(config),
        "stage1": {
            "detections": [_det(d) for d in dets],
            "best_confidence": best,
            "kept": len(kept),
            "prompt_mask_empty": prompt_empty,
            "empty_after": stage1_empty,
        },
        "stage2": {"box_threshold": high, "text_threshold": text_high, "attempts": attempts},
    }
    return TwoStageResult([m for m in masks], source, info)
