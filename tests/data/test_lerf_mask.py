"""LERF-mask split and GT indexing on small fixtures in the published layout."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from cobgs.data.lerf_mask import LERF_PROMPTS, lerf_split, read_lerf_gt
from cobgs.errors import DataError


def make_scene(root, n=7, train=(0, 2, 4, 6), gt=None, size=(16, 12)):
    """images/frame_XXXXX.jpg, images_train/ with the ``train`` indices, and test_mask/.

    ``gt``: {test idx (folder name): {prompt: mask array or None for an empty mask}}.
    """
    w, h = size
    (root / "images").mkdir(parents=True)
    (root / "images_train").mkdir()
    img = np.full((h, w, 3), 128, np.uint8)
    for i in range(n):
        cv2.imwrite(str(root / "images" / f"frame_{i:05d}.jpg"), img)
        if i in train:
            cv2.imwrite(str(root / "images_train" / f"frame_{i:05d}.jpg"), img)
    for idx, prompts in (gt or {}).items():
        d = root / "test_mask" / str(idx)
        d.mkdir(parents=True)
        for prompt, m in prompts.items():
            cv2.imwrite(str(d / f"{prompt}.png"), np.zeros((h, w), np.uint8) if m is None else m)
    return root


def test_split_follows_images_train(tmp_path):
    root = make_scene(tmp_path / "s")
    train, test = lerf_split(root)
    assert train == ["frame_00000", "frame_00002", "frame_00004", "frame_00006"]
    assert test == ["frame_00001", "frame_00003", "frame_00005"]


def test_gt_index_is_position_among_sorted_test_views(tmp_path):
    m = np.zeros((12, 16), np.uint8)
    m[2:6, 3:9] = 255
    root = make_scene(tmp_path / "s", gt={0: {"red apple": m, "egg": None}, "02": {"red apple": m},
                                          7: {"egg": m}, "notes": {}})
    gt = read_lerf_gt(root)
    assert gt.test_views == ["frame_00001", "frame_00003", "frame_00005"]
    assert set(gt.masks) == {("frame_00001", "red apple"), ("frame_00001", "egg"), ("frame_00005", "red apple")}
    assert gt.prompts == ["egg", "red apple"]
    assert gt.views_without_gt == ["frame_00003"]
    assert sorted(gt.unknown_indices) == ["7", "notes"]  # index past the test views, non-numeric
    assert gt.views_for("red apple") == ["frame_00001", "frame_00005"]
    j = gt.to_json()
    assert {(r["view"], r["prompt"]) for r in j["masks"]} == set(gt.masks)


def test_errors_name_the_folder(tmp_path):
    root = make_scene(tmp_path / "s")
    with pytest.raises(DataError, match="test_mask"):
        read_lerf_gt(root)
    (root / "test_mask").mkdir()
    with pytest.raises(DataError, match="no <idx>/<prompt>.png"):
        read_lerf_gt(root)
    bad = make_scene(tmp_path / "b", train=(0, 1, 2, 3, 4, 5, 6))
    with pytest.raises(DataError, match="no test view"):
        lerf_split(bad)
    cv2.imwrite(str(root / "images_train" / "stray.jpg"), np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(DataError, match="not in images/"):
        lerf_split(root)


def test_published_prompts():
    assert len(LERF_PROMPTS["figurines"]) == 7 and len(LERF_PROMPTS["ramen"]) == 6
    assert len(LERF_PROMPTS["teatime"]) == 10 and "rubber duck with red hat" in LERF_PROMPTS["figurines"]
