"""Multi-object refinement bookkeeping (docs/method.md §2 multi-object)."""

from __future__ import annotations

import math

import pytest
import torch

from cobgs.errors import InputError
from cobgs.gaussians.ply import load_ply
from cobgs.refine.alternation import OBJECT_ID, OBJECT_LOGITS, assign_object_ids, masks_for, refine_objects
from cobgs.configs import RefineConfig
from cobgs.refine.scores import LABEL
from cobgs.refine.segment import export_objects, object_index
from refine_fixtures import tiny_scene

L9 = math.log(9.0)


def test_assign_object_ids():
    logits = torch.tensor([[3.0, -3.0], [2.5, 2.9], [0.0, 0.0], [-5.0, 2.3], [2.0, 2.1]])
    # > logit(0.9) = 2.197: row 0 -> object 1; row 1 -> both, the higher (2) wins;
    # row 2 none; row 3 -> object 2; row 4 -> below 0.9 for object 1, above for 2.
    assert assign_object_ids(logits).tolist() == [1, 2, 0, 2, 0]


def test_refine_objects_bookkeeping(tmp_path):
    model, views, extent = tiny_scene(n_views=3)
    masks = {"ball": masks_for(views, "ball"), "cube": masks_for(views, "cube")}
    cfg = RefineConfig(mask_stages=2, stage_length_views=9, split_size_fraction=0.0)
    mo = refine_objects(model, views, masks, extent, cfg, progress=False)
    m = mo.model
    n = len(m)
    assert mo.object_names == ["ball", "cube"]
    assert m.data[OBJECT_LOGITS].shape == (n, 2) and m.data[OBJECT_ID].dtype == torch.int64
    assert torch.equal(m.data[OBJECT_ID], assign_object_ids(m.data[OBJECT_LOGITS]))
    # The last object's labels are its refinement's labels; the earlier object got a
    # label-only pass on the final scene.
    assert torch.equal(m.data[OBJECT_LOGITS][:, 1], m.data[LABEL].detach())
    assert mo.final_pass[1] is None and mo.final_pass[0].kind == "label_pass"
    assert mo.final_pass[0].gaussians_start == mo.final_pass[0].gaussians_end == n
    assert mo.final_pass[0].iterations == 27  # 9 V: 27 Adam steps of lr 0.1 can pass logit(0.9)
    # Sequential: the second refinement starts from the scene the first one left.
    r0, r1 = mo.refinements
    assert r0["num_gaussians_start"] == len(model) and r1["num_gaussians_start"] == r0["num_gaussians_end"]
    assert r1["num_gaussians_end"] == n
    assert r0["splits"] > 0
    # Both objects found something, mostly on disjoint Gaussians.
    ball, cube = mo.result("ball"), mo.result("cube")
    assert ball.foreground.sum() > 0 and cube.foreground.sum() > 0
    assert (ball.foreground & cube.foreground).sum() < 0.1 * min(ball.foreground.sum(), cube.foreground.sum())
    assert torch.equal(ball.foreground, m.data[OBJECT_LOGITS][:, 0] > L9)
    # object_id lookup matches the per-object sets where they do not overlap.
    ids = object_index(mo, "ball")
    only_ball = ball.foreground & ~cube.foreground
    assert set(torch.nonzero(only_ball)[:, 0].tolist()) <= set(ids.tolist())
    # Export: one PLY per object plus the background without any object.
    paths = export_objects(mo, tmp_path)
    assert len(load_ply(paths["ball"])) == int(ball.foreground.sum())
    assert len(load_ply(paths["cube"])) == int(cube.foreground.sum())
    bg = (m.data[OBJECT_LOGITS] < -L9).all(1)
    assert len(load_ply(paths["_background"])) == int(bg.sum())
    assert len(model) == 600 and OBJECT_LOGITS not in model.data  # input untouched
    with pytest.raises(InputError):
        mo.result("teapot")


def test_refine_objects_input_errors():
    model, views, extent = tiny_scene(n_views=2)
    with pytest.raises(InputError):
        refine_objects(model, views, {}, extent, progress=False)
    with pytest.raises(InputError, match="masks"):
        refine_objects(model, views, {"ball": [None]}, extent, progress=False)
