"""End to end on the synthetic ``demo`` scene: generate, train briefly, refine, compare.

The scene is generated into a temporary folder at a reduced size, the baseline is trained
with the known cameras of ``transforms.json`` (no SfM) from surface points of the exact
geometry, then COB-GS (released defaults, full 22·V schedule) and the no-split peer segment
the objects that touch others. Heavy (a couple of minutes on 2 cores): marked slow.
"""

from __future__ import annotations

import pytest
import torch

from cobgs.data.readers import read_scene
from cobgs.data.synth.scene import generate_scene
from cobgs.gaussians.model import GaussianModel
from cobgs.refine.methods import run_method
from cobgs.refine.alternation import masks_for
from cobgs.configs import RefineConfig
from cobgs.refine.segment import evaluate_masks
from cobgs.train.optimize import evaluate, train
from cobgs.configs import TrainConfig
from refine_fixtures import synthetic_surface_points

pytestmark = pytest.mark.slow

SIZE = dict(width_px=128, height_px=96, num_views=24)


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    root = generate_scene(tmp_path_factory.mktemp("demo") / "scene", "demo", seed=0, progress=False, **SIZE)
    scene = read_scene(root)
    xyz, rgb = synthetic_surface_points("demo", 0, scene.train, 6000, **SIZE)
    init = GaussianModel.from_points(xyz, rgb, sh_degree=1)
    # Densification interval scaled with the run length (10 its here): a dense baseline
    # (~20k Gaussians). With the unscaled 100-it interval the baseline stays at ~16k larger
    # Gaussians; COB-GS still wins clearly on the crate there, but not on the can (within
    # the noise of 3 test views), so the recipe is pinned.
    cfg = TrainConfig(iterations=700, sh_degree=1, max_gaussians=20000, seed=0, scale_densify_interval=True)
    res = train(scene, cfg, model=init, progress=False, evaluate_test=False)
    return scene, res.model


@pytest.mark.parametrize("obj", ["crate", "can"])
def test_cobgs_beats_nosplit_on_boundaries(demo, obj):
    scene, model = demo
    train_masks, test_masks = masks_for(scene.train, obj), masks_for(scene.test, obj)
    cob = run_method("cobgs", model, scene.train, train_masks, scene.extent, progress=False, object_name=obj)
    ref = run_method("nosplit", model, scene.train, train_masks, scene.extent, progress=False, object_name=obj)
    mask_stages = [s for s in cob.stages if s.kind == "mask"]
    assert len(cob.stages) == 11 and len(mask_stages) == 6
    # Splitting shrinks the set of large ambiguous Gaussians stage after stage (the
    # no-split run sees the same ambiguous set every stage: scores depend on geometry only).
    assert mask_stages[-1].ambiguous_large < 0.75 * mask_stages[0].ambiguous_large
    ref_stages = [s.ambiguous for s in ref.stages]
    # (the no-split row trains labels for the whole 22·V: 11 mask stages)
    assert len(ref_stages) == 11 and ref_stages == [ref_stages[0]] * 11 and ref_stages[0] == mask_stages[0].ambiguous
    # RAEM (the default, paper variant) prunes only ambiguous Gaussians below a pixel's footprint
    assert sum(s.split for s in cob.stages) > 0 and 0 <= cob.stages[-1].pruned <= cob.ambiguous_final
    # ... and the segmentation boundary on held-out views improves over the no-split peer.
    e_cob = evaluate_masks(cob, scene.test, test_masks)
    e_ref = evaluate_masks(ref, scene.test, test_masks)
    assert e_cob["views"] == e_ref["views"] == len(scene.test)
    assert e_cob["biou"] > e_ref["biou"] + 0.01
    assert e_cob["iou"] > e_ref["iou"]
    # Joint refinement does not degrade the texture (paper Table 4: measured before RAEM).
    bg = scene.background
    before = cob.model_before_raem()
    assert len(before) == len(cob.model) + cob.stages[-1].pruned
    assert evaluate(before, scene.test, bg)["psnr"] >= evaluate(model, scene.test, bg)["psnr"] - 0.1
