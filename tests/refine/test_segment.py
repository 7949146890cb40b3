"""Segmentation: thresholds, extraction, PLY export, evaluation renders and metrics."""

from __future__ import annotations

import math

import pytest
import torch

from cobgs.errors import InputError
from cobgs.gaussians.ply import load_ply
from cobgs.refine.alternation import masks_for, refine
from cobgs.configs import RefineConfig
from cobgs.refine.result import RefineResult
from cobgs.render.image import render_image
from cobgs.refine.segment import (
    evaluate_masks,
    export_ply,
    extract,
    label_sets,
    render_object_mask,
    render_object_rgb,
    render_removed_rgb,
    subset,
)
from refine_fixtures import three_gaussians, tiny_model, tiny_scene


def _result(model, fg, bg, values=None) -> RefineResult:
    n = len(model)
    return RefineResult(method="test", object_name="obj", model=model, foreground=fg, background=bg,
                        mask_values=torch.ones(n) if values is None else values)


def test_label_thresholds_are_on_the_sigmoid():
    p = torch.tensor([0.95, 0.9, 0.5, 0.1, 0.05, 0.899, 0.101])
    fg, bg = label_sets(torch.log(p / (1 - p)))
    assert fg.tolist() == [True, False, False, False, False, False, False]
    assert bg.tolist() == [False, False, False, False, True, False, False]
    fg2, bg2 = label_sets(torch.log(p / (1 - p)), fg_threshold=0.5, bg_threshold=0.5)
    assert fg2.tolist() == [True, True, False, False, False, True, False]
    with pytest.raises(InputError):
        label_sets(torch.zeros(2), fg_threshold=0.1, bg_threshold=0.9)


def test_subset_copies_rows_and_extras():
    m = tiny_model(50)
    m.add_extra("mask_logit", torch.arange(50.0), fill=0.0)
    m.add_extra("object_id", torch.arange(50) % 3, fill=0)
    idx = torch.tensor([3, 7, 11])
    s = subset(m, idx)
    assert len(s) == 3 and s.extras == ["mask_logit", "object_id"]
    for k in m.data:
        assert torch.equal(s.data[k].detach(), m.data[k].detach()[idx])
    b = torch.zeros(50, dtype=torch.bool)
    b[idx] = True
    assert torch.equal(subset(m, b).means, s.means)
    with torch.no_grad():
        s.data["means"].add_(1.0)
    assert not torch.equal(s.means, m.means[idx])  # an independent copy
    with pytest.raises(InputError):
        subset(m, torch.zeros(3, dtype=torch.bool))


def test_export_ply_round_trip(tmp_path):
    m = tiny_model(40)
    fg = torch.arange(40) < 15
    bg = torch.arange(40) >= 20
    r = _result(m, fg, bg)
    paths = export_ply(r, tmp_path, "thing")
    assert sorted(p.name for p in paths.values()) == ["thing_background.ply", "thing_object.ply"]
    obj, back = load_ply(paths["object"]), load_ply(paths["background"])
    assert len(obj) == 15 and len(back) == 20 and obj.extras == []
    assert torch.allclose(obj.means, m.means[:15]) and torch.allclose(back.sh, m.sh[20:])
    e = extract(r, "background")
    assert len(e) == 20
    with pytest.raises(InputError):
        extract(r, "middle")


def test_object_mask_render_uses_foreground_only_and_threshold():
    model, view = three_gaussians()
    with torch.no_grad():
        model.data["opacity_logits"].fill_(5.0)  # near-opaque, so the mask channel passes 0.5
    only_a = _result(model, torch.tensor([True, False, False]), torch.tensor([False, True, True]))
    soft = render_object_mask(only_a, view.camera, soft=True)
    hard = render_object_mask(only_a, view.camera)
    assert soft.shape == (32, 32) and hard.dtype == torch.bool
    assert torch.equal(hard, soft > 0.5)
    assert hard.any() and not hard[:, 16:].any()  # A is on the left; B (centre) is not rendered
    low = _result(model, torch.tensor([True, False, False]), torch.tensor([False, True, True]),
                  values=torch.full((3,), 0.4))
    assert not render_object_mask(low, view.camera).any()  # values 0.4 never reach 0.5
    empty = _result(model, torch.zeros(3, dtype=torch.bool), torch.ones(3, dtype=torch.bool))
    assert not render_object_mask(empty, view.camera).any()


def test_rgb_renders_object_and_removal():
    model, views, _ = tiny_scene(n_views=1)
    fg = model.means[:, 0] < 0
    r = _result(model, fg, ~fg)
    cam = views[0].camera
    obj = render_object_rgb(r, cam, (0.0, 0.0, 0.0))
    rem = render_removed_rgb(r, cam, (0.0, 0.0, 0.0))
    assert torch.allclose(obj, render_image(subset(model, fg), cam, (0.0, 0.0, 0.0)))
    assert torch.allclose(rem, render_image(subset(model, ~fg), cam, (0.0, 0.0, 0.0)))
    none = _result(model, torch.zeros(len(model), dtype=torch.bool), torch.ones(len(model), dtype=torch.bool))
    assert torch.all(render_object_rgb(none, cam, (1.0, 1.0, 1.0)) == 1.0)


def test_evaluate_masks_metrics_and_skips():
    model, views, extent = tiny_scene(n_views=3)
    masks = masks_for(views, "ball")
    r = refine(model, views, masks, extent, RefineConfig(mask_stages=2, stage_length_views=4), progress=False)
    gts = [masks[0], None, torch.zeros_like(masks[2])]
    ev = evaluate_masks(r, views, gts)
    assert ev["views"] == 1 and ev["skipped"] == ["v1", "v2"]
    pred = render_object_mask(r, views[0].camera)
    inter = (pred & masks[0]).sum().item()
    union = (pred | masks[0]).sum().item()
    assert ev["iou"] == pytest.approx(inter / union)
    assert 0.0 <= ev["biou"] <= 1.0 and ev["acc"] == pytest.approx((pred == masks[0]).float().mean().item())
    keep_empty = evaluate_masks(r, views, gts, skip_empty_gt=False)
    assert keep_empty["views"] == 2
    none = evaluate_masks(r, views, [None] * 3)
    assert none["views"] == 0 and math.isnan(none["iou"])


def test_evaluate_masks_visible_mode_lets_occluders_hide_the_object():
    """With visible-pixel GT the object-only render counts hidden object pixels as false
    positives; ``visible=True`` renders the occluder (with mask value 0) in front."""
    from cobgs.render.camera import Camera
    from cobgs.data.scene import View
    from cobgs.gaussians.model import GaussianModel

    W = H = 32
    cam = Camera(K=torch.tensor([[50.0, 0, 16.0], [0, 50.0, 16.0], [0, 0, 1]]), viewmat=torch.eye(4),
                 width=W, height=H, name="cam")
    # object: a wide flat disc at z = 3; occluder: an opaque disc covering its right half at z = 2
    means = torch.tensor([[0.0, 0.0, 3.0], [0.45, 0.0, 2.0]])
    log_scales = torch.log(torch.tensor([[0.4, 0.4, 0.01], [0.25, 0.6, 0.01]]))
    model = GaussianModel(means, log_scales, torch.tensor([[1.0, 0, 0, 0]] * 2), torch.full((2,), 8.0),
                          torch.zeros(2, 1, 3), torch.zeros(2, 0, 3))
    r = _result(model, torch.tensor([True, False]), torch.tensor([False, True]))
    from cobgs.refine.segment import visible_object_mask

    amodal = render_object_mask(r, cam)
    vis = visible_object_mask(r, cam)
    assert amodal.sum() > vis.sum() > 0  # the occluder hides part of the object
    gt = vis.clone()  # the visible-pixel GT
    view = View(camera=cam, image=torch.zeros(H, W, 3), name="cam", masks={"obj": gt})
    ev_vis = evaluate_masks(r, [view], [gt], visible=True)
    ev_obj = evaluate_masks(r, [view], [gt])
    assert ev_vis["iou"] == pytest.approx(1.0)
    assert ev_obj["iou"] == pytest.approx(gt.sum().item() / amodal.sum().item()) and ev_obj["iou"] < 0.95
