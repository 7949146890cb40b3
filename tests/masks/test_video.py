"""SAM2 video propagation through the stand-in graphs."""

from __future__ import annotations

import numpy as np
import pytest

from cobgs.errors import InputError, ModelError
from cobgs.masks.api import generate_masks_from_points
from cobgs.masks.encoder_cache import EncoderCache
from cobgs.masks.manifest import load_manifest
from cobgs.masks.postprocess import NO_OBJ_SCORE
from cobgs.masks.sam2_models import Sam2Models
from cobgs.masks.video import VideoPredictor

from . import fakes, scenes

MOVING = [scenes.Frame("red", x=8 + 4 * i, y=10 + 2 * i) for i in range(5)]


def _predictor(root, paths, **cache_kw):
    sam = Sam2Models(load_manifest(root).sam2)
    return VideoPredictor(sam, EncoderCache(sam, paths, **cache_kw))


def _run(pred, frame, **prompt):
    pred.add_prompt(frame, 1, **prompt)
    out = {f: m[1] for f, m in pred.propagate(frame)}
    if frame > 0:
        out.update({f: m[1] for f, m in pred.propagate(frame, reverse=True)})
    return [out[i] for i in range(pred.num_frames)]


@pytest.fixture(scope="module")
def moving(tmp_path_factory):
    return scenes.write_sequence(tmp_path_factory.mktemp("moving"), MOVING)


def test_tracks_moving_object_both_ways(models_dir, moving):
    paths, gts = moving
    pred = _predictor(models_dir, paths)
    f = MOVING[2]
    masks = _run(pred, 2, box=(f.x, f.y, f.x + scenes.SIDE, f.y + scenes.SIDE))
    for m, gt in zip(masks, gts):
        assert m.shape == gt.shape and scenes.iou(m, gt) > 0.9


def test_multimask_for_one_point_single_mask_for_box(models_dir, moving):
    paths, _ = moving
    pred = _predictor(models_dir, paths)
    f = MOVING[0]
    pred.add_prompt(0, 1, box=(f.x, f.y, f.x + 12, f.y + 12))
    pred.add_prompt(0, 2, points=[[f.x + 6, f.y + 6]], labels=[1])
    pred.add_prompt(0, 3, points=[[f.x + 2, f.y + 2], [f.x + 10, f.y + 10]], labels=[1, 1])
    # stand-in pointers carry their token index in channel 0
    assert pred.banks[1].cond[0].obj_ptr[0] == 0  # box: token 0 (stable)
    assert pred.banks[2].cond[0].obj_ptr[0] == 2  # one point: best IoU of 1..3
    assert pred.banks[3].cond[0].obj_ptr[0] == 0  # two points: single mask
    # planes are logit - 0.3 (token 0) and logit (token 2): the stored logits show which
    d = pred.banks[2].cond[0].low_res.max() - pred.banks[1].cond[0].low_res.max()
    assert d == pytest.approx(0.3, abs=1e-5)
    # tracked frames are multimask: token 2's pointer
    frame, _ = next(iter(pred.propagate(1, 1, obj_ids=[1])))
    assert pred.banks[1].non_cond[1].obj_ptr[0] == 2


def test_object_score_gating_on_absent_object(models_dir, tmp_path):
    seq = [scenes.Frame("red"), scenes.Frame("red", x=22), scenes.Frame(None)]
    paths, _ = scenes.write_sequence(tmp_path, seq)
    pred = _predictor(models_dir, paths)
    masks = _run(pred, 0, box=(20, 16, 32, 28))
    assert masks[1].any() and not masks[2].any()
    absent = pred.banks[1].non_cond[2]
    assert absent.object_score <= 0 and np.all(absent.low_res == NO_OBJ_SCORE)
    assert absent.maskmem[0, 3] == 0  # the memory says "not present"


def test_renamed_reordered_export_gives_identical_masks(models_dir, models_renamed, moving):
    paths, _ = moving
    box = dict(box=(8, 10, 20, 22))
    a = _run(_predictor(models_dir, paths), 0, **box)
    b = _run(_predictor(models_renamed, paths), 0, **box)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    spec = load_manifest(models_renamed).sam2.graphs["mask_decoder"]
    assert {t.ours: t.theirs for t in spec.inputs}["point_coords"] == "coords"


def test_sam20_variant_tracks(models_v20, moving):
    paths, gts = moving
    masks = _run(_predictor(models_v20, paths), 0, box=(8, 10, 20, 22))
    assert all(scenes.iou(m, g) > 0.9 for m, g in zip(masks, gts))


@pytest.mark.parametrize("kw", [dict(with_ptr_inputs=False, memenc_score=False),
                                dict(planes=3), dict(planes=1), dict(curr_nchw=True),
                                dict(concat_ptr=True), dict(encoder_adds_no_mem_embed=True)])
def test_layout_variants_track(tmp_path, moving, kw):
    root = fakes.build_sam2(tmp_path / "m", **kw)
    paths, gts = moving
    masks = _run(_predictor(root, paths), 0, box=(8, 10, 20, 22))
    assert all(scenes.iou(m, g) > 0.9 for m, g in zip(masks, gts))


def test_encoder_no_mem_embed_flag_recovers_raw_features(models_dir, tmp_path, moving):
    root = fakes.build_sam2(tmp_path / "m", encoder_adds_no_mem_embed=True)
    paths, _ = moving
    raw = _predictor(models_dir, paths).cache.get(0).feats
    got = _predictor(root, paths).cache.get(0).feats
    np.testing.assert_allclose(got, raw, atol=1e-6)  # 0.5 in channel 0 was subtracted


def test_concat_pointer_layout_feeds_pointer_count(tmp_path, moving):
    from cobgs.masks.session import SessionOptions

    root = fakes.build_sam2(tmp_path / "m", concat_ptr=True)
    paths, _ = moving
    sam = Sam2Models(load_manifest(root).sam2, SessionOptions(trace_shapes=True))
    pred = VideoPredictor(sam, EncoderCache(sam, paths))
    pred.add_prompt(0, 1, box=(8, 10, 20, 22))
    list(pred.propagate(0, 2))
    shapes = sam.sessions["memory_attention"].stats.shapes
    steps = pred.banks[1].steps
    for st, sh in zip(steps, shapes):
        n_ptr = 4 * len(st.pointers)
        assert sh["memory"] == (4096 * len(st.memory) + n_ptr, 1, 64)
        assert sh["num_obj_ptr_tokens"] == (1,)


def test_image_only_export_prompts_but_refuses_video(models_image_only, moving, tmp_path):
    paths, gts = moving
    pred = _predictor(models_image_only, paths)
    f = MOVING[2]
    box = (f.x, f.y, f.x + 12, f.y + 12)
    m = pred.add_prompt(2, 1, box=box)
    assert scenes.iou(m, gts[2]) > 0.9
    with pytest.raises(ModelError, match="image-only.*cannot propagate"):
        next(iter(pred.propagate(2)))
    res = generate_masks_from_points(paths[2:3], 0, models_image_only, tmp_path / "one",
                                     box=box)
    assert res.sources == ["prompt"]
    with pytest.raises(ModelError, match="image-only"):
        generate_masks_from_points(paths, 2, models_image_only, tmp_path / "all", box=box)


def test_mask_prompt_is_the_output_and_tracks(models_dir, moving):
    paths, gts = moving
    pred = _predictor(models_dir, paths)
    out = pred.add_mask(0, 1, gts[0])
    np.testing.assert_array_equal(out, gts[0])
    masks = {f: m[1] for f, m in pred.propagate(0)}
    assert all(scenes.iou(masks[i], gts[i]) > 0.9 for i in range(len(paths)))


def test_encoder_cache_spills_to_disk_without_reencoding(models_dir, moving):
    paths, _ = moving
    f = MOVING[3]
    box = (f.x, f.y, f.x + 12, f.y + 12)
    ref = _run(_predictor(models_dir, paths), 3, box=box)
    pred = _predictor(models_dir, paths, max_bytes_in_memory=1)  # everything spills
    got = _run(pred, 3, box=box)
    for a, b in zip(ref, got):
        np.testing.assert_array_equal(a, b)
    assert pred.cache.max_encodes_per_frame() == 1 and pred.cache._disk
    pred.cache.close()


def test_bad_prompts_rejected(models_dir, moving):
    paths, _ = moving
    pred = _predictor(models_dir, paths)
    with pytest.raises(InputError, match="box or at least one point"):
        pred.add_prompt(0, 1)
    with pytest.raises(InputError, match="frame index must be in"):
        pred.add_prompt(99, 1, box=(0, 0, 1, 1))
    with pytest.raises(InputError, match="labels must be 1"):
        pred.add_prompt(0, 1, points=[[1, 1]], labels=[2])
    with pytest.raises(InputError, match="no prompted frame"):
        pred.track(1, 5, reverse=False)


def test_prompt_on_a_tracked_frame_is_a_correction(models_dir, moving):
    """As SAM2's video predictor (Grounded-SAM-2's copy, the authors' flow): decoded through
    memory attention with the frame's previous logits, clamped to ±32, as the mask input;
    kept as a tracked frame that propagation does not track again; the other object's
    output on that frame kept too, its memory re-encoded from the binarised mask."""
    paths, gts = moving
    pred = _predictor(models_dir, paths)
    f0 = MOVING[0]
    pred.add_prompt(0, 1, box=(f0.x, f0.y, f0.x + scenes.SIDE, f0.y + scenes.SIDE))
    pred.add_prompt(0, 2, points=[[f0.x + 6, f0.y + 6]], labels=[1])
    list(pred.propagate(0))
    bank, other = pred.banks[1], pred.banks[2]
    before = bank.non_cond[3]
    before_other = other.non_cond[3].maskmem.copy()
    seen = []
    decode = pred.models.decode

    def spy(embed, frame, coords, labels, mask_input=None):
        seen.append(None if mask_input is None else mask_input.copy())
        return decode(embed, frame, coords, labels, mask_input)

    pred.models.decode = spy
    calls = pred.models.call_counts()
    f3 = MOVING[3]
    mask = pred.add_prompt(3, 1, box=(f3.x, f3.y, f3.x + scenes.SIDE, f3.y + scenes.SIDE))
    after = pred.models.call_counts()
    assert after["memory_attention"] - calls["memory_attention"] == 1  # decoded with memory
    np.testing.assert_array_equal(seen[0], np.clip(before.low_res, -32, 32))
    assert 3 not in bank.cond and bank.non_cond[3] is not before and 3 in bank.kept
    assert scenes.iou(mask, gts[3]) > 0.9
    assert 3 in other.kept and not np.array_equal(other.non_cond[3].maskmem, before_other)
    # propagating again keeps frame 3 (no step there) and tracks the others anew
    steps = [s.frame for s in bank.steps]
    out = {f: m for f, m in pred.propagate(0)}
    tracked_now = [s.frame for s in bank.steps][len(steps):]
    assert 3 not in tracked_now and tracked_now == [1, 2, 4]
    np.testing.assert_array_equal(out[3][1], mask)
    # "condition": the old rule, a new conditioning frame decoded without memory
    pred2 = _predictor(models_dir, paths)
    pred2.add_prompt(0, 1, box=(f0.x, f0.y, f0.x + scenes.SIDE, f0.y + scenes.SIDE))
    list(pred2.propagate(0))
    n = pred2.models.call_counts()["memory_attention"]
    pred2.add_prompt(3, 1, box=(f3.x, f3.y, f3.x + scenes.SIDE, f3.y + scenes.SIDE), on_tracked="condition")
    assert 3 in pred2.banks[1].cond and pred2.models.call_counts()["memory_attention"] == n
    with pytest.raises(InputError, match="on_tracked"):
        pred2.add_prompt(3, 1, box=(1, 1, 5, 5), on_tracked="maybe")
