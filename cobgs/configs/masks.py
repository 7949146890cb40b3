"""Configs of the prompt routes: two-stage text prompting and scribbles (cobgs.masks)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar


from .checks import check_params


# -- two-stage masks and scribbles (cobgs.masks) ------------------------------------------
@dataclass(frozen=True)
class TwoStageConfig:
    """Thresholds of Alg. 1 as the authors ran it (docs/method.md §4)."""

    prompt_frame: int = 0
    box_threshold: float = 0.3
    text_threshold: float = 0.45
    keep_ratio_of_best: float = 0.7
    stage2_box_threshold_min: float = 0.6
    stage2_ratio_of_best: float = 0.85
    stage2_text_threshold_min: float = 0.65
    run_stage2: bool = True
    # The authors' flow (their Grounded-SAM-2 script) by default; the alternatives are
    # named so a run can say which it used.
    # stage2_reprompt: "correct" = a stage-2 box on a frame already tracked corrects it
    #   (SAM2's video predictor: decoded with memory and the frame's previous mask, kept as
    #   a tracked frame); "condition" = a new conditioning frame decoded without memory
    #   (trusts the detector over the memory: every later frame attends to that box).
    stage2_reprompt: str = "correct"
    # stage2_backward: also propagate a stage-2 prompt backward to the start of its run of
    #   empty frames (the authors go forward only, so a run's frames before the first
    #   detection stay empty; backward fills them when the object was only half visible).
    stage2_backward: bool = False
    # empty_rule: a frame is empty when the "first_object"'s mask is (the authors: the first
    #   kept detection in Grounding DINO's query order), or when the "union" of every
    #   object's mask is (one object lost among several then does not count as empty).
    empty_rule: str = "first_object"
    # detection_order: object ids follow Grounding DINO's "query" order (upstream
    #   predict()), or "confidence" (best first); stage-2 boxes pair with the objects in it.
    detection_order: str = "query"

    RANGES: ClassVar[dict] = {
        "prompt_frame": "[0, 1e7]", "box_threshold": "[0, 1]", "text_threshold": "[0, 1]",
        "keep_ratio_of_best": "[0, 1]", "stage2_box_threshold_min": "[0, 1]", "stage2_ratio_of_best": "[0, 1]",
        "stage2_text_threshold_min": "[0, 1]"}
    CHOICES: ClassVar[dict] = {"stage2_reprompt": ("correct", "condition"), "empty_rule": ("first_object", "union"),
                               "detection_order": ("query", "confidence")}

    def __post_init__(self) -> None:
        check_params(self)


@dataclass(frozen=True)
class ScribbleConfig:
    """Sampling of skeleton points; the thresholds are the protocol's."""

    keep_positive_above: float = 0.98
    keep_negative_above: float = 0.995
    seed: int = 0
    # A scribble pixel has some colour channel above this (8-bit images; 0 = any non-zero
    # channel, the protocol's: pure red or blue strokes and anti-aliased edges count).
    binarize_above: int = 0
    # a scribble too short to leave any point still contributes its middle pixel
    at_least_one_per_scribble: bool = True

    RANGES: ClassVar[dict] = {"keep_positive_above": "[0, 1]", "keep_negative_above": "[0, 1]",
                              "seed": "[0, 2147483647]", "binarize_above": "[0, 254]"}

    def __post_init__(self) -> None:
        check_params(self)


