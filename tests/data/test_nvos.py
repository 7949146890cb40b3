"""NVOS labels reader on small fixtures in the published layout."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from cobgs.data.nvos import NVOS_TASKS, nvos_scene_of, read_gt_mask, read_nvos_task
from cobgs.errors import DataError


def _png(path, arr):
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), arr)


def make_labels(root, task="fern", target=None, reference=None, size=(40, 30), colour_gt=False):
    """A labels folder for one task: masks/, reference_image/, scribbles/ (scribbles at 1/4)."""
    _, t, r = NVOS_TASKS.get(task, (task, "T0", "R0"))
    target, reference = target or t, reference or r
    w, h = size
    img = np.full((h, w, 3), 90, np.uint8)
    _png(root / "masks" / task / f"{target}.JPG", img)
    gt = np.zeros((h, w), np.uint8)
    gt[8:20, 10:30] = 255
    _png(root / "masks" / task / f"{target}_mask.png", np.dstack([gt] * 3) if colour_gt else gt)
    _png(root / "reference_image" / task / f"{reference}.JPG", img)
    pos = np.zeros((h // 4 + 1, w // 4 + 1), np.uint8)
    pos[3, 2:8] = 255
    neg = np.zeros_like(pos)
    neg[0, 0:4] = 255
    _png(root / "scribbles" / task / "pos_0.png", pos)
    _png(root / "scribbles" / task / "neg_0.png", neg)
    return root


def test_reads_published_task(tmp_path):
    make_labels(tmp_path, "horns_left")
    t = read_nvos_task(tmp_path, "horns_left")
    assert t.scene == "horns"
    assert (t.target, t.reference) == NVOS_TASKS["horns_left"][1:]
    assert t.gt_mask.name == f"{t.target}_mask.png"
    assert [p.name for p in t.positive_scribbles] == ["pos_0.png"]
    assert [p.name for p in t.negative_scribbles] == ["neg_0.png"]
    assert t.target_image is not None and t.reference_image is not None
    j = t.to_json()
    assert j["task"] == "horns_left" and j["gt_mask"].endswith("_mask.png")


def test_unknown_task_derives_names_from_files(tmp_path):
    make_labels(tmp_path, "mycup_left", target="A1", reference="B2")
    t = read_nvos_task(tmp_path, "mycup_left")
    assert (t.scene, t.target, t.reference) == ("mycup", "A1", "B2")
    assert nvos_scene_of("trex") == "trex" and nvos_scene_of("a_b") == "a"


def test_gt_mask_is_grey_uint8(tmp_path):
    make_labels(tmp_path, "fern", colour_gt=True)
    g = read_gt_mask(read_nvos_task(tmp_path, "fern").gt_mask)
    assert g.dtype == np.uint8 and g.shape == (30, 40)
    assert set(np.unique(g)) == {0, 255} and (g > 128).sum() == 12 * 20


@pytest.mark.parametrize("breakage, message", [
    ("no_labels", "NVOS labels folder not found"),
    ("no_task", "no masks/fern/ folder"),
    ("no_gt", "exactly one <target>_mask.png"),
    ("wrong_target", "published target"),
    ("no_scribbles", "scribbles folder not found"),
    ("no_positive", "no positive scribble"),
])
def test_missing_or_wrong_files_are_named(tmp_path, breakage, message):
    root = tmp_path / "labels"
    make_labels(root, "fern")
    if breakage == "no_labels":
        root = tmp_path / "absent"
    elif breakage == "no_task":
        import shutil

        shutil.rmtree(root / "masks" / "fern")
    elif breakage == "no_gt":
        (root / "masks" / "fern" / "IMG_4027_mask.png").unlink()
    elif breakage == "wrong_target":
        (root / "masks" / "fern" / "IMG_4027_mask.png").rename(root / "masks" / "fern" / "IMG_0000_mask.png")
    elif breakage == "no_scribbles":
        import shutil

        shutil.rmtree(root / "scribbles" / "fern")
    elif breakage == "no_positive":
        (root / "scribbles" / "fern" / "pos_0.png").unlink()
    with pytest.raises(DataError, match=message):
        read_nvos_task(root, "fern")


def test_scribble_files_are_matched_by_pos_neg_substrings(tmp_path):
    """Any image whose name holds pos / neg (any case); visualisations are ignored; a name
    holding both is refused with the file named."""
    root = make_labels(tmp_path / "labels", "fern")
    sdir = root / "scribbles" / "fern"
    dot = np.zeros((8, 11), np.uint8)
    dot[3, 3:6] = 255
    for name in ("scribble_pos_1.png", "NEG_2.png", "pos_vis.png", "overlay.png"):
        _png(sdir / name, dot)
    t = read_nvos_task(root, "fern")
    assert [p.name for p in t.positive_scribbles] == ["pos_0.png", "scribble_pos_1.png"]
    assert [p.name for p in t.negative_scribbles] == ["NEG_2.png", "neg_0.png"]
    _png(sdir / "pos_neg_3.png", dot)
    with pytest.raises(DataError, match="both 'pos' and 'neg'") as info:
        read_nvos_task(root, "fern")
    assert "pos_neg_3.png" in str(info.value)
