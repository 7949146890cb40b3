"""Evaluation protocols (cobgs.evaluate.protocols): rules that decide the reported numbers."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from cobgs.evaluate import protocols as E
from cobgs.errors import InputError


def box(h, w, y0, y1, x0, x1, value=255):
    m = np.zeros((h, w), np.uint8)
    m[y0:y1, x0:x1] = value
    return m


def test_compare_counts_and_metrics():
    gt = box(10, 10, 0, 4, 0, 5)  # 20 px
    pred = box(10, 10, 0, 4, 1, 6)  # 20 px, 16 overlap
    s = E.compare_masks(pred, gt)
    assert (s.tp, s.fp, s.fn, s.tn) == (16, 4, 4, 76)
    assert s.iou == pytest.approx(16 / 24) and s.acc == pytest.approx(92 / 100)
    assert not s.resized and (s.height, s.width) == (10, 10)
    assert E.compare_masks(gt, gt).biou == 1.0


def test_binarised_strictly_above_128():
    gt = box(4, 4, 0, 2, 0, 4)
    at = box(4, 4, 0, 2, 0, 4, value=128)  # JPEG-ish grey at exactly 128 is background
    above = box(4, 4, 0, 2, 0, 4, value=129)
    assert E.compare_masks(at, gt).iou == 0.0
    assert E.compare_masks(above, gt).iou == 1.0
    # bool and float predictions count as 0/255
    assert E.compare_masks(gt > 0, gt).iou == 1.0
    assert E.compare_masks((gt > 0).astype(np.float32), gt).iou == 1.0


def test_prediction_resized_nearest_to_gt():
    pred = np.zeros((3, 4), np.uint8)
    pred[1, 1:3] = 255
    gt = np.repeat(np.repeat(pred, 4, 0), 4, 1)  # 12 x 16, exact 4x nearest upsampling
    s = E.compare_masks(pred, gt)
    assert s.resized and (s.height, s.width) == (12, 16) and s.iou == 1.0
    # a prediction at a non-integer ratio: PIL nearest keeps it binary, no blur at 128
    r = E.resize_nearest(pred, 7, 9)
    assert r.shape == (7, 9) and set(np.unique(r)) <= {0, 255}


def test_exact_scores_skip_missing_and_empty_gt():
    gts = {"a": box(8, 8, 0, 4, 0, 4), "b": np.zeros((8, 8), np.uint8), "c": None}
    preds = {"a": box(8, 8, 0, 4, 0, 2), "b": box(8, 8, 0, 2, 0, 2), "c": box(8, 8, 0, 1, 0, 1)}
    r = E.exact_scores(preds, gts)
    assert r["views"] == 1 and r["iou"] == pytest.approx(0.5)
    assert set(r["skipped"]) == {"b", "c"}
    keep = E.exact_scores(preds, gts, skip_empty_gt=False)
    assert keep["views"] == 2 and keep["per_view"]["b"]["iou"] == 0.0
    with pytest.raises(InputError, match="no prediction"):
        E.exact_scores({}, {"a": gts["a"]})


def test_nvos_summary_means_over_tasks():
    s1 = E.compare_masks(box(4, 4, 0, 2, 0, 4), box(4, 4, 0, 2, 0, 4))
    s2 = E.compare_masks(box(4, 4, 0, 2, 0, 2), box(4, 4, 0, 2, 0, 4))
    out = E.nvos_summary({"fern": s1, "trex": s2})
    assert out["tasks"] == 2
    assert out["miou"] == pytest.approx((1.0 + 0.5) / 2)
    assert out["macc"] == pytest.approx((1.0 + 12 / 16) / 2)


def test_lerf_means_per_prompt_then_over_prompts(tmp_path):
    h = w = 8
    gt_full = box(h, w, 0, 4, 0, 4)
    views = ["v0", "v1", "v2", "v3"]

    def write(name, arr):
        p = tmp_path / f"{name}.png"
        cv2.imwrite(str(p), arr)
        return p

    # prompt A: one view, perfect; prompt B: three views, all wrong, plus an empty GT.
    a = E.lerf_prompt_scores({"v0": gt_full}, {"v0": write("a0", gt_full)}, views)
    b_paths = {v: write(f"b{i}", gt_full) for i, v in enumerate(views[:3])}
    b_paths["v3"] = write("b3", np.zeros((h, w), np.uint8))
    b = E.lerf_prompt_scores({v: box(h, w, 4, 8, 4, 8) for v in views}, b_paths, views)
    assert a["iou"] == 1.0 and a["views"] == 1 and set(a["skipped"]) == {"v1", "v2", "v3"}
    # v3's GT is empty and the prediction is not: scored 0, as Gaussian Grouping does
    assert b["iou"] == 0.0 and b["views"] == 4 and b["skipped"] == {}
    assert b["empty_gt"] == {"v3": "empty GT, prediction not empty: IoU 0"}
    assert (b["empty_gt_zero"], b["empty_gt_nan"]) == (1, 0)
    s = E.lerf_summary({"A": a, "B": b, "C": {"views": 0, "iou": float("nan"), "biou": float("nan")}})
    assert s["miou"] == pytest.approx(0.5)  # not 0.25: prompts weigh equally, not views
    assert s["prompts"] == 2 and s["prompts_without_gt"] == ["C"]


def test_lerf_empty_gt_follows_gaussian_groupings_rule(tmp_path):
    """Hand computation of eval_lerf_mask.py's rule: IoU = |P∩G| / |P∪G| per GT file, 0/0
    = NaN left out of the mean. v0: half overlap -> 1/3; v1: empty GT, non-empty prediction
    -> 0; v2: both empty -> NaN. Mean over finite values = (1/3 + 0) / 2."""
    h = w = 8

    def write(name, arr):
        p = tmp_path / f"{name}.png"
        cv2.imwrite(str(p), arr)
        return p

    empty = np.zeros((h, w), np.uint8)
    paths = {"v0": write("g0", box(h, w, 0, 4, 0, 4)), "v1": write("g1", empty),
             "v2": write("g2", empty)}
    preds = {"v0": box(h, w, 0, 4, 2, 6), "v1": box(h, w, 5, 7, 5, 7), "v2": empty}
    r = E.lerf_prompt_scores(preds, paths, ["v0", "v1", "v2"])
    assert r["per_view"]["v0"]["iou"] == pytest.approx(8 / 24)
    assert r["per_view"]["v1"]["iou"] == 0.0 and r["per_view"]["v1"]["biou"] == 0.0
    assert np.isnan(r["per_view"]["v2"]["iou"]) and np.isnan(r["per_view"]["v2"]["biou"])
    assert r["iou"] == pytest.approx((8 / 24 + 0.0) / 2)
    assert r["views"] == 2 and (r["empty_gt_zero"], r["empty_gt_nan"]) == (1, 1)
    assert set(r["skipped"]) == {"v2"} and set(r["empty_gt"]) == {"v1", "v2"}


def test_psnr_of_8bit_renders():
    ref = np.zeros((4, 4, 3), np.uint8)
    img = ref.copy()
    img[0, 0, 0] = 255  # one channel of one pixel off by 1.0: MSE = 1 / 48
    r = E.psnr_scores({"v": img}, {"v": ref})
    assert r["psnr"] == pytest.approx(10 * math.log10(48))
    # float references are quantised like a saved PNG: 128.3 / 255 compares as 128
    grey = np.full((4, 4, 3), 128, np.uint8)
    assert E.psnr_scores({"v": grey}, {"v": np.full((4, 4, 3), 128.3 / 255, np.float32)})["psnr"] == math.inf
    with pytest.raises(InputError, match="no render"):
        E.psnr_scores({}, {"v": ref})


def test_aggregate_two_levels():
    rows = [
        {"scene": "s1", "method": "m", "object": "a", "iou": 1.0},
        {"scene": "s1", "method": "m", "object": "b", "iou": 0.0},
        {"scene": "s1", "method": "m", "object": "c", "iou": 0.5},
        {"scene": "s2", "method": "m", "object": "a", "iou": 0.9},
        {"scene": "s2", "method": "x", "object": "a", "iou": float("nan")},
    ]
    by = {r["method"]: r for r in E.aggregate(rows, ["iou"])}
    assert by["m"]["iou"] == pytest.approx((0.5 + 0.9) / 2)  # scene means, then the mean
    assert by["m"]["scenes"] == 2 and by["m"]["objects"] == 4
    assert math.isnan(by["x"]["iou"])
    per_scene = E.aggregate(rows, ["iou"], by=("scene", "method"))
    assert {(r["scene"], r["method"]): r["iou"] for r in per_scene}[("s1", "m")] == pytest.approx(0.5)
