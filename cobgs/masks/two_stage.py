"""Two-stage mask generation from a text prompt (paper Alg. 1, released thresholds).

Stage 1: Grounding DINO on the prompt frame at box threshold 0.3 / text threshold 0.45;
boxes with confidence >= 0.7 x the best become box prompts, one tracked object each
(SAM2's video predictor takes one box per object); propagate forward, and backward when
the prompt frame is not the first. A frame is empty when the union of its object masks has
no foreground pixel.

Stage 2: scanning forward, each still-empty frame is detected again at box threshold
max(0.6, 0.85 x best stage-1 confidence); when boxes are found they prompt that frame
(paired with the objects in confidence order) and the objects are propagated over the
maximal run of consecutive empty frames holding it (FindMaxSub): forward to its end, and
backward to its start when ``stage2_backward`` (upstream only went forward).

A stage-2 prompt becomes a new conditioning frame of the same memory bank, so tracking
afterwards attends to both the stage-1 and the stage-2 prompts.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field
from typing import Dict, List, Optional

import numpy as np

from cobgs.configs import TwoStageConfig  # noqa: F401 (defined there)
from cobgs.errors import CobgsError, InputError

from .gdino import Detection, GroundingDino
from .video import VideoPredictor


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
    dets = detector.detect(cache.rgb(p), prompt, config.box_threshold, config.text_threshold)
    if not dets:
        raise NoDetectionError(
            f"Grounding DINO found no '{prompt}' on the prompt frame {p} at box threshold "
            f"{config.box_threshold}; choose another prompt frame or prompt text"
        )
    best = dets[0].confidence
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
        masks[frame] = np.logical_or.reduce(list(per_obj.values()))
        source[frame] = label if masks[frame].any() else "empty"

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
        found = detector.detect(cache.rgb(f), prompt, high, text_high)
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
            predictor.add_prompt(f, obj, box=d.box_xyxy)
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
