"""Two-stage generation (Alg. 1): which frames are prompted, propagated, left empty."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from cobgs.errors import InputError
from cobgs.masks.api import generate_masks
from cobgs.masks.two_stage import NoDetectionError
from cobgs.configs import TwoStageConfig

from . import scenes


def _read(out_dir, paths):
    return [np.asarray(Image.open(out_dir / f"{p.stem}.png")) for p in paths]


def test_red_gone_green(models_dir, red_green, tmp_path):
    paths, gts = red_green
    out = tmp_path / "masks" / "square"
    res = generate_masks(paths, "red square", models_dir, out)
    assert res.sources == (["prompt"] + ["stage1"] * 4 + ["empty"] * 5 + ["stage2_prompt"]
                           + ["stage2"] * 4)
    assert res.empty == [f"{i:04d}" for i in range(5, 10)]
    masks = _read(out, paths)
    for m, gt in zip(masks, gts):
        assert m.dtype == np.uint8 and m.shape == gt.shape and set(np.unique(m)) <= {0, 255}
        assert scenes.iou(m > 0, gt) > 0.9
    log = json.loads(res.log_path.read_text())
    assert res.log_path == tmp_path / "masks" / "square.json"
    assert log["stage1"]["best_confidence"] == pytest.approx(0.9)
    assert log["stage1"]["kept"] == 1  # the 0.35 distractor is below 0.7 x 0.9
    assert log["stage1"]["prompt_mask_empty"] is False
    assert log["stage1"]["empty_after"] == list(range(5, 15))
    assert log["stage2"]["box_threshold"] == pytest.approx(0.765)
    att = log["stage2"]["attempts"]
    assert [a["frame"] for a in att] == [5, 6, 7, 8, 9, 10]
    assert att[-1]["run"] == [5, 14] and all(not a["detections"] for a in att[:-1])
    assert [f["source"] for f in log["frames"]] == res.sources
    # encoder at most once per frame; stage 2 (forward only, as the authors) reads 10..14
    assert log["encoder_runs_max_per_frame"] == 1 and log["graph_calls"]["image_encoder"] == 15
    assert log["encoder_cache_hits"] == 5
    # decoder / memory encoder: 15 in stage 1, then the correction of 10 + 4 forward; the
    # correction goes through memory attention (14 + 1 + 4), unlike a conditioning prompt
    assert log["graph_calls"]["mask_decoder"] == 20
    assert log["graph_calls"]["memory_encoder"] == 20
    assert log["graph_calls"]["memory_attention"] == 19
    assert log["detector_calls"] == 1 + 6


def test_prompt_frame_in_the_middle_tracks_backwards(models_dir, red_green, tmp_path):
    paths, gts = red_green
    res = generate_masks(paths, "square", models_dir, tmp_path / "o",
                         config=TwoStageConfig(prompt_frame=2))
    assert res.sources[:5] == ["stage1", "stage1", "prompt", "stage1", "stage1"]
    assert res.sources[10] == "stage2_prompt"


def test_without_stage2_the_reappearing_object_stays_empty(models_dir, red_green, tmp_path):
    paths, _ = red_green
    res = generate_masks(paths, "square", models_dir, tmp_path / "o",
                         config=TwoStageConfig(run_stage2=False))
    assert res.sources[10:] == ["empty"] * 5


def test_stage2_threshold_and_backward_over_the_run(models_dir, tmp_path):
    # green returns half hidden (confidence 0.45 < 0.765) at frames 3-4, fully at 5-6
    seq = ([scenes.Frame("red", x=10), scenes.Frame(None), scenes.Frame(None)]
           + [scenes.Frame("green", visible_rows=6)] * 2 + [scenes.Frame("green")] * 2)
    paths, gts = scenes.write_sequence(tmp_path / "seq", seq)
    res = generate_masks(paths, "square", models_dir, tmp_path / "a",
                         config=TwoStageConfig(stage2_backward=True))
    assert res.sources == ["prompt", "empty", "empty", "stage2", "stage2", "stage2_prompt",
                           "stage2"]
    log = json.loads(res.log_path.read_text())
    assert [a["frame"] for a in log["stage2"]["attempts"]] == [1, 2, 3, 4, 5]
    assert log["stage2"]["attempts"][-1]["run"] == [1, 6]
    masks = _read(tmp_path / "a", paths)
    assert scenes.iou(masks[3] > 0, gts[3]) > 0.9
    # the authors' forward-only stage 2 (the default) leaves the half-hidden frames empty
    res = generate_masks(paths, "square", models_dir, tmp_path / "b")
    assert res.sources[1:5] == ["empty"] * 4 and res.sources[5:] == ["stage2_prompt", "stage2"]


def test_nothing_on_prompt_frame_is_a_clear_error(models_dir, red_green, tmp_path):
    paths, _ = red_green
    # the stand-in detector knows only "square": an apple is found nowhere
    with pytest.raises(NoDetectionError, match="no 'apple' on the prompt frame 6"):
        generate_masks(paths, "apple", models_dir, tmp_path / "o",
                       config=TwoStageConfig(prompt_frame=6))
    assert not (tmp_path / "o").exists()  # nothing half-written


def test_text_path_needs_grounding_dino(models_v20, red_green, tmp_path):
    from cobgs.masks.manifest import ModelsNotConfiguredError

    with pytest.raises(ModelsNotConfiguredError, match="no 'groundingdino' model"):
        generate_masks(red_green[0], "square", models_v20, tmp_path / "o")


def test_empty_prompt_mask_is_reported(models_dir, tmp_path, caplog):
    # the detector sees the square, but the box lies beside it: SAM2 (stand-in) finds
    # nothing inside, which must be said, not silently propagated
    from cobgs.masks.api import generate_masks_from_points

    paths, _ = scenes.write_sequence(tmp_path / "s", [scenes.Frame("red")] * 2)
    caplog.set_level("WARNING", logger="cobgs.masks")
    res = generate_masks_from_points(paths, 0, models_dir, tmp_path / "o", box=(40, 2, 60, 10))
    assert res.sources == ["empty", "empty"]
    assert "empty mask for the prompt on frame 0" in caplog.text


def test_empty_prompt_mask_in_two_stage_is_logged(models_dir, tmp_path, caplog):
    from cobgs.masks.gdino import Detection
    from cobgs.masks.two_stage import run_two_stage
    from cobgs.masks.encoder_cache import EncoderCache
    from cobgs.masks.manifest import load_manifest
    from cobgs.masks.sam2_models import Sam2Models
    from cobgs.masks.video import VideoPredictor

    class BoxBesideTheObject:  # a detector whose box misses the object
        def detect(self, rgb, caption, box_threshold, text_threshold, order="confidence"):
            return [Detection((40.0, 2.0, 60.0, 10.0), 0.9, "square")]

    paths, _ = scenes.write_sequence(tmp_path / "s", [scenes.Frame("red")] * 2)
    sam = Sam2Models(load_manifest(models_dir).sam2)
    caplog.set_level("WARNING", logger="cobgs.masks")
    res = run_two_stage(BoxBesideTheObject(), VideoPredictor(sam, EncoderCache(sam, paths)),
                        "square", TwoStageConfig(run_stage2=False))
    assert res.log["stage1"]["prompt_mask_empty"] is True
    assert "empty mask for the detected box" in caplog.text


def test_empty_rule_judges_the_first_object_as_the_authors(models_dir, tmp_path):
    """Two kept boxes, the first (in query order) beside the object: the authors' rule calls
    every frame empty (their script looks at the first object's mask); "union" does not.
    The mask written is the union either way."""
    from cobgs.masks.encoder_cache import EncoderCache
    from cobgs.masks.gdino import Detection
    from cobgs.masks.manifest import load_manifest
    from cobgs.masks.sam2_models import Sam2Models
    from cobgs.masks.two_stage import run_two_stage
    from cobgs.masks.video import VideoPredictor

    f = scenes.Frame("red")

    class TwoBoxes:
        def detect(self, rgb, caption, box_threshold, text_threshold, order="confidence"):
            beside = Detection((40.0, 2.0, 60.0, 10.0), 0.8, "square")
            real = Detection((f.x, f.y, f.x + scenes.SIDE, f.y + scenes.SIDE), 0.9, "square")
            return [beside, real] if order == "query" else [real, beside]

    paths, gts = scenes.write_sequence(tmp_path / "s", [f] * 3)
    sam = Sam2Models(load_manifest(models_dir).sam2)
    out = {}
    for rule in ("first_object", "union"):
        res = run_two_stage(TwoBoxes(), VideoPredictor(sam, EncoderCache(sam, paths)), "square",
                            TwoStageConfig(run_stage2=False, empty_rule=rule))
        out[rule] = res
        assert all(scenes.iou(m, gt) > 0.9 for m, gt in zip(res.masks, gts))  # the union
    assert out["first_object"].source == ["empty"] * 3
    assert out["union"].source == ["prompt", "stage1", "stage1"]
    with pytest.raises(InputError, match="empty_rule"):
        TwoStageConfig(empty_rule="any")
