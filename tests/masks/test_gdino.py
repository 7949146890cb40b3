"""Grounding DINO: offline tokenisation, host-built masks, upstream thresholds."""

from __future__ import annotations

import numpy as np
import pytest

from cobgs.errors import InputError
from cobgs.masks.gdino import GroundingDino, Tokenizer, normalise_caption, phrase_masks
from cobgs.masks.manifest import load_manifest

from . import fakes, scenes


@pytest.fixture(scope="module")
def tok(tmp_path_factory):
    path = tmp_path_factory.mktemp("vocab") / "vocab.txt"
    fakes.write_vocab(path)
    return Tokenizer(path, 256, (101, 102, 1012, 1029))


def test_caption_normalised():
    assert normalise_caption("  Red Apple ") == "red apple ."
    assert normalise_caption("red apple.") == "red apple."
    with pytest.raises(InputError, match="empty"):
        normalise_caption("   ")


def test_tokens_position_ids_and_phrase_mask(tok):
    t = tok("Red square. green apple")
    # [CLS] red square . green apple . [SEP]
    assert t.input_ids.tolist() == [[101, 2001, 2000, 1012, 2002, 2003, 1012, 102]]
    assert t.input_ids.dtype == np.int64 and t.attention_mask.dtype == bool
    # positions restart at 0 after every special token; the '.' closes its phrase
    assert t.position_ids.tolist() == [[0, 0, 1, 2, 0, 1, 2, 0]]
    m = t.text_token_mask[0]
    assert m.shape == (8, 8) and m.dtype == bool
    blocks = [[0], [1, 2, 3], [4, 5, 6], [7]]
    for blk in blocks:
        for i in range(8):
            for j in range(8):
                if i in blk:
                    assert m[i, j] == (j in blk), (i, j)
    assert not t.token_type_ids.any() and t.attention_mask.all()


def test_phrase_masks_matches_a_direct_construction():
    ids = np.array([101, 5, 6, 1012, 7, 1029, 8, 9, 1012, 102])
    mask, pos = phrase_masks(ids, (101, 102, 1012, 1029))
    assert pos.tolist() == [0, 0, 1, 2, 0, 1, 0, 1, 2, 0]
    want = np.zeros((10, 10), bool)
    for a, b in [(0, 1), (1, 4), (4, 6), (6, 9), (9, 10)]:
        want[a:b, a:b] = True
    np.testing.assert_array_equal(mask, want)


def test_long_caption_truncated(tmp_path):
    path = tmp_path / "vocab.txt"
    fakes.write_vocab(path)
    t = Tokenizer(path, 6, (101, 102, 1012, 1029))("red square red square red square")
    assert t.input_ids.shape == (1, 6) and t.text_token_mask.shape == (1, 6, 6)


@pytest.fixture(scope="module")
def detector(models_dir):
    return GroundingDino(load_manifest(models_dir).gdino)


def test_detects_only_visible_object_with_upstream_thresholds(detector):
    img, gt = scenes.render(scenes.Frame("red", x=20, y=16))
    dets = detector.detect(img, "red square", 0.3, 0.45)
    # query 0 (0.9) and the weak distractor (0.35) pass 0.3; best first
    assert [round(d.confidence, 3) for d in dets] == [0.9, 0.35]
    assert dets[0].box_xyxy == pytest.approx((20, 16, 32, 28), abs=1e-3)
    assert dets[0].phrase == "red square"
    # box threshold is strict ">" and text threshold never removes a box
    assert len(detector.detect(img, "red square", 0.35, 0.99)) == 1
    assert detector.detect(img, "red square", 0.3, 0.99)[0].phrase == ""
    # absent object, or a caption without the word the stand-in knows: nothing above 0.6
    empty, _ = scenes.render(scenes.Frame(None))
    assert detector.detect(empty, "red square", 0.6, 0.65) == []
    assert detector.detect(img, "green apple", 0.3, 0.45) == []


def test_partially_visible_object_has_lower_confidence(detector):
    img, _ = scenes.render(scenes.Frame("green", visible_rows=6))
    dets = detector.detect(img, "square", 0.3, 0.45)
    assert dets[0].confidence == pytest.approx(0.45, abs=1e-4)


def test_keep_aspect_size_is_upstreams_resize():
    from cobgs.masks.manifest import keep_aspect_size

    assert keep_aspect_size(756, 1008) == (800, 1066)  # LLFF at 1/4: the long side truncated
    assert keep_aspect_size(800, 1200) == (800, 1200)
    assert keep_aspect_size(1008, 756) == (1066, 800)  # portrait
    assert keep_aspect_size(1000, 3000) == (444, 1332)  # short side round(1333 / 3) = 444, long 3 x 444
    assert keep_aspect_size(48, 64, short_side=48) == (48, 64)


def test_a_graph_traced_for_another_aspect_is_refused_unless_stretch_is_asked(scratch_models, red_green, tmp_path):
    from cobgs.errors import ModelError
    from cobgs.masks.api import generate_masks

    # the stand-in graph is traced at 48x64; upstream's rule (short side 800) wants 800x1066
    fakes.edit_manifest(scratch_models, lambda d: d["groundingdino"]["preprocess"].update(short_side=800))
    det = GroundingDino(load_manifest(scratch_models).gdino)
    img, _ = scenes.render(scenes.Frame("red"))
    with pytest.raises(ModelError, match=r"traced at 48x64, but Grounding DINO resizes a 48x64 frame.*"
                                         r"--size 800 1066.*resize = \"stretch\""):
        det.detect(img, "red square", 0.3, 0.45)
    with pytest.raises(ModelError, match="--size 800 1066"):  # at load, before any frame is encoded
        generate_masks(red_green[0], "red square", scratch_models, tmp_path / "o")
    assert not (tmp_path / "o").exists()
    fakes.edit_manifest(scratch_models, lambda d: d["groundingdino"]["preprocess"].update(resize="stretch"))
    det = GroundingDino(load_manifest(scratch_models).gdino)
    assert det.detect(img, "red square", 0.3, 0.45)[0].confidence == pytest.approx(0.9)


def test_query_order_is_upstreams_and_confidence_order_is_best_first(detector):
    # a barely visible square scores below the 0.35 distractor (query 1)
    img, _ = scenes.render(scenes.Frame("red", visible_rows=2))
    by_query = detector.detect(img, "red square", 0.05, 0.45, order="query")
    by_conf = detector.detect(img, "red square", 0.05, 0.45)
    assert len(by_query) == 2 and by_query[0].confidence < by_query[1].confidence
    assert [d.confidence for d in by_conf] == sorted((d.confidence for d in by_query), reverse=True)
    with pytest.raises(ValueError, match="order"):
        detector.detect(img, "red square", 0.05, 0.45, order="random")
