"""The peers (docs/method.md §3) on hand-built cases, and the run_method dispatch."""

from __future__ import annotations

import pytest
import torch

from cobgs.errors import InputError
from cobgs.refine.peers import (
    flashsplat_votes,
    nosplit_config,
    run_flashsplat,
    run_flashsplat_multi,
    run_sa3d,
)
from cobgs.refine.alternation import masks_for
from cobgs.refine.methods import run_method
from cobgs.configs import FlashSplatConfig, RefineConfig, SA3DConfig
from cobgs.refine.scores import pixel_labels_from_mask
from refine_fixtures import three_gaussians, tiny_scene


def test_flashsplat_votes_are_alpha_t_sums_per_label():
    model, view = three_gaussians()
    lab = pixel_labels_from_mask(view.masks["obj"], 32, 32)
    w = flashsplat_votes(model, [view, view], [lab, lab], 2)
    assert w.shape == (3, 2)
    assert w[0, 0] == 0 and w[0, 1] > 0  # A: object pixels only
    assert w[1, 0] == pytest.approx(float(w[1, 1]), rel=1e-5)  # B: symmetric on the edge
    assert torch.all(w[2] == 0)  # C: never seen


@pytest.mark.parametrize("bias, expected", [(0.0, [True, False, False]), (0.3, [True, False, False]),
                                            (-0.1, [True, True, True]), (-1.5, [True, True, True])])
def test_flashsplat_bias_and_unseen_rule(bias, expected):
    model, view = three_gaussians()
    r = run_flashsplat(model, [view], [view.masks["obj"]], FlashSplatConfig(background_bias=bias), object_name="obj")
    # A wins the object; B is a tie (object only with a negative bias); C, unseen, goes to
    # the background unless the bias is negative.
    assert r.foreground.tolist() == expected
    assert torch.equal(r.background, ~r.foreground)
    assert r.method == "flashsplat" and len(r.model) == len(model)
    assert torch.all(r.mask_values == 1)


def test_flashsplat_strong_bias_removes_weak_object_gaussians():
    model, view = three_gaussians()
    mask = view.masks["obj"].clone()
    mask[:, :] = False
    mask[:, :15] = True  # shift the edge one pixel left: B is now mostly background
    r0 = run_flashsplat(model, [view], [mask], FlashSplatConfig(background_bias=0.0))
    rn = run_flashsplat(model, [view], [mask], FlashSplatConfig(background_bias=-0.9))
    assert not r0.foreground[1] and rn.foreground[1]


def test_flashsplat_multi_object_l1_rule():
    model, view = three_gaussians()
    left = view.masks["obj"]
    right = ~left
    res = run_flashsplat_multi(model, [view], {"left": [left], "right": [right]})
    assert set(res) == {"left", "right"}
    # A is all "left"; B splits evenly (share 0.5 = sum of the others: not above, so neither);
    # C unseen: neither.
    assert res["left"].foreground.tolist() == [True, False, False]
    assert res["right"].foreground.tolist() == [False, False, False]
    biased = run_flashsplat_multi(model, [view], {"left": [left], "right": [right]},
                                  FlashSplatConfig(background_bias=-0.1))
    assert biased["right"].foreground.tolist() == [False, True, True]


def test_flashsplat_multi_object_bias_normalises_the_pair_first(monkeypatch):
    """upstream render.py multi_instance_opt: with a non-zero slackness the [others,
    object] pair is L2-normalised per Gaussian before the bias is added to "others"."""
    import cobgs.refine.peers as peers

    model, view = three_gaussians()
    left = view.masks["obj"]
    # L1 shares per Gaussian [background, left, right]: G0 0/0.6/0.4, G1 0.5/0.5/0, G2 unseen.
    votes = torch.tensor([[0.0, 6.0, 4.0], [1.0, 1.0, 0.0], [0.0, 0.0, 0.0]], dtype=torch.float64)
    monkeypatch.setattr(peers, "flashsplat_votes", lambda *a, **k: votes.clone())
    masks = {"left": [left], "right": [~left]}
    # bias 0: plain shares. G0: 0.6 > 0.4 -> left.
    r0 = run_flashsplat_multi(model, [view], masks)
    assert r0["left"].foreground.tolist() == [True, False, False]
    # bias 0.25: unnormalised 0.6 > 0.4 + 0.25 fails; L2-normalised 0.832 > 0.555 + 0.25 holds.
    r = run_flashsplat_multi(model, [view], masks, FlashSplatConfig(background_bias=0.25))
    assert r["left"].foreground.tolist() == [True, False, False]
    # bias -0.3: right's pair for G0 (others 0.6, right 0.4) -> (0.832, 0.555): 0.555 > 0.532;
    # G1 (1, 0) -> 0 > 0.7 fails; G2 (0, 0): 0 > -0.3 holds.
    r = run_flashsplat_multi(model, [view], masks, FlashSplatConfig(background_bias=-0.3))
    assert r["right"].foreground.tolist() == [True, False, True]
    # An object nobody voted for gets no Gaussian, whatever the bias (upstream skips it).
    votes[:, 2] = 0
    r = run_flashsplat_multi(model, [view], masks, FlashSplatConfig(background_bias=-0.5))
    assert r["right"].foreground.tolist() == [False, False, False]


def test_sa3d_two_passes_prune_and_threshold():
    model, view = three_gaussians()
    r = run_sa3d(model, [view], [view.masks["obj"]], SA3DConfig(passes=2), object_name="obj", progress=False)
    assert [s.kind for s in r.stages] == ["sa3d_pass", "sa3d_pass"]
    # Pass 1 (one Adam step of lr 1): A's raw label rises to 1; B, on the edge, rises too
    # (the 0.3-weighted background term is outweighed: SA3D-GS's foreground bias); C has
    # no gradient and stays at 0 -> out of the optimised set (label <= 0): "dropped", not
    # pruned — it stays in the scene.
    assert r.stages[0].dropped == 1 and r.stages[0].pruned == 0
    assert all(s.gaussians_end == 3 for s in r.stages) and len(r.model) == 3
    assert r.summary()["pruned"] == 0 and r.summary()["dropped"] == 1
    assert r.foreground.tolist() == [True, True, False]
    lab = r.model.data["sa3d_label"]
    assert lab[0] > 0.5 and lab[1] > 0.5 and torch.isinf(lab[2])
    assert "sa3d_label" not in model.data  # input untouched
    # official render: the raw labels of the foreground composited, bar 0.1
    assert r.mask_threshold == 0.1
    assert torch.equal(r.mask_values, torch.where(r.foreground, lab, torch.zeros(())))


def test_sa3d_official_keeps_label_above_zero_strict_above_half():
    model, view = three_gaussians()
    cfg = SA3DConfig(passes=1, lr=0.3)  # one step of lr 0.3: labels of A and B reach 0.3
    off = run_sa3d(model, [view], [view.masks["obj"]], cfg, progress=False)
    strict = run_sa3d(model, [view], [view.masks["obj"]], SA3DConfig.strict(passes=1, lr=0.3), progress=False)
    lab = off.model.data["sa3d_label"]
    assert 0 < lab[0] < 0.5 and 0 < lab[1] < 0.5
    assert off.foreground.tolist() == [True, True, False]  # label > 0
    assert strict.foreground.tolist() == [False, False, False]  # label > 0.5
    assert strict.mask_threshold == 0.5 and torch.all(strict.mask_values == 1)
    from cobgs.refine.segment import render_object_mask

    m = render_object_mask(off, view.camera, soft=True)
    assert torch.equal(render_object_mask(off, view.camera), m > 0.1)  # the method's own bar
    assert torch.equal(render_object_mask(off, view.camera, threshold=0.5), m > 0.5)


def _opaque_three():
    """three_gaussians with opacity 0.95: the label render of A and B passes 0.5 near
    their centres (at opacity 0.5 it never does)."""
    model, view = three_gaussians()
    with torch.no_grad():
        model.data["opacity_logits"][:] = 3.0
    return model, view


def _render_of(model, view, labels):
    from cobgs.refine.scores import render_label_mask

    return render_label_mask(model, view.camera, labels, None).image[..., 0].detach()


def test_sa3d_skips_views_whose_render_disagrees_with_the_mask():
    """Official pass-1 rule: from the second view on, a view whose mask rendered from the
    current labels (> 0.5) has IoU < 0.5 with its mask is skipped; the order is fixed."""
    model, view = _opaque_three()
    half = view.masks["obj"]  # the left half: A inside, B on its edge
    # After the first step (Adam, lr 1) A's and B's labels are 1: the render (> 0.5) of
    # those labels is a mask the current labels agree with (IoU 1) ...
    agree = _render_of(model, view, torch.tensor([1.0, 1.0, 0.0])) > 0.5
    wrong = ~agree  # ... and its complement one they do not (IoU 0)
    r = run_sa3d(model, [view, view, view], [half, wrong, agree], SA3DConfig(passes=1), progress=False)
    assert r.stages[0].skipped_views == 1 and r.stages[0].iterations == 2
    # Without the rule the wrong mask trains too: other labels.
    r0 = run_sa3d(model, [view, view, view], [half, wrong, agree], SA3DConfig(passes=1, skip_iou=0.0),
                  progress=False)
    assert r0.stages[0].skipped_views == 0 and r0.stages[0].iterations == 3
    assert not torch.equal(r.model.data["sa3d_label"], r0.model.data["sa3d_label"])
    # Skipping the view is training on the other two alone.
    r2 = run_sa3d(model, [view, view], [half, agree], SA3DConfig(passes=1), progress=False)
    assert torch.equal(r.model.data["sa3d_label"], r2.model.data["sa3d_label"])
    # The first view is never skipped, even though nothing is labelled before it.
    r1 = run_sa3d(model, [view], [wrong], SA3DConfig(passes=1), progress=False)
    assert r1.stages[0].skipped_views == 0 and r1.stages[0].iterations == 1
    with pytest.raises(InputError, match="order"):
        SA3DConfig(order="shuffled")


def test_sa3d_gate_binarises_the_render_at_half_not_at_the_evaluation_bar():
    """train_seg.py:229-231 thresholds the rendered mask at 0.5 for the IoU gate; 0.1 is
    only render.py's evaluation bar. A mask equal to the render above 0.1 (32 px here)
    covers the render above 0.5 (6 px) with IoU 6/32: skipped by the official gate,
    accepted by a gate at 0.1."""
    model, view = _opaque_three()
    m = _render_of(model, view, torch.tensor([1.0, 1.0, 0.0]))
    loose, tight = m > 0.1, m > 0.5
    assert int(tight.sum()) / int(loose.sum()) < 0.5
    half = view.masks["obj"]
    r = run_sa3d(model, [view, view], [half, loose], SA3DConfig(passes=1), progress=False)
    assert r.stages[0].skipped_views == 1
    r = run_sa3d(model, [view, view], [half, tight], SA3DConfig(passes=1), progress=False)
    assert r.stages[0].skipped_views == 0
    r = run_sa3d(model, [view, view], [half, loose], SA3DConfig(passes=1, gate_threshold=0.1), progress=False)
    assert r.stages[0].skipped_views == 0


def test_sa3d_second_pass_has_no_gate_and_skips_exactly_the_first_pass_skips(monkeypatch):
    """train_seg.py:246-250: the second pass tests nothing; it skips the views the first
    skipped. The gate is scripted: view 1 passes and view 2 fails in pass 1; any test in
    pass 2 would fail every view."""
    import cobgs.refine.peers as peers

    model, view = _opaque_three()
    half = view.masks["obj"]
    calls = []

    def scripted_iou(pred, labels):
        calls.append(len(calls))
        return [0.9, 0.1][len(calls) - 1] if len(calls) <= 2 else 0.0

    monkeypatch.setattr(peers, "_mask_iou", scripted_iou)
    r = run_sa3d(model, [view, view, view], [half, half, half], SA3DConfig(passes=2), progress=False)
    assert len(calls) == 2  # the first pass's two gated views only
    assert [s.skipped_views for s in r.stages] == [1, 1]
    assert [s.iterations for s in r.stages] == [2, 2]
    # The same as training views 0 and 1 twice without any gate.
    monkeypatch.undo()
    ref = run_sa3d(model, [view, view], [half, half], SA3DConfig(passes=2, skip_iou=0.0), progress=False)
    assert torch.equal(r.model.data["sa3d_label"], ref.model.data["sa3d_label"])
    assert torch.equal(r.foreground, ref.foreground)


def test_sa3d_keeps_every_gaussian_when_no_label_is_positive():
    """GaussianModel.segment: when no label is > 0 it keeps the whole cloud, after pass 1
    and in the final segmentation; the strict variant keeps none."""
    model, view = three_gaussians()
    empty = torch.zeros_like(view.masks["obj"])  # every pixel background: labels only fall
    r = run_sa3d(model, [view], [empty], SA3DConfig(passes=2), progress=False)
    assert r.stages[0].dropped == 0  # none removed between the passes
    assert r.foreground.tolist() == [True, True, True]
    lab = r.model.data["sa3d_label"]
    assert lab[0] < 0 and lab[1] < 0 and lab[2] == 0
    # The official render composites those raw labels: nothing passes 0.1.
    from cobgs.refine.segment import render_object_mask

    assert not bool(render_object_mask(r, view.camera).any())
    s = run_sa3d(model, [view], [empty], SA3DConfig.strict(passes=2), progress=False)
    assert s.foreground.tolist() == [False, False, False] and s.stages[0].dropped == 3


def test_sa3d_binary_variant_is_the_official_training_rendered_at_half():
    model, view = _opaque_three()
    half = view.masks["obj"]
    off = run_sa3d(model, [view, view], [half, half], SA3DConfig(), progress=False)
    b = run_sa3d(model, [view, view], [half, half], SA3DConfig.binary(), progress=False)
    assert torch.equal(off.foreground, b.foreground)
    assert torch.equal(off.model.data["sa3d_label"], b.model.data["sa3d_label"])
    assert b.mask_threshold == 0.5 and torch.all(b.mask_values == 1)
    assert off.mask_threshold == 0.1


def test_sa3d_unnormalised_weighted_loss():
    model, view = three_gaussians()
    with torch.no_grad():
        model.data["means"][1, 0] = 0.02  # B's centre at 16.5 px: ~55 % of its weight is object
    mask = view.masks["obj"]
    r = run_sa3d(model, [view, view], [mask, mask], SA3DConfig(passes=1, skip_iou=0.0), progress=False)
    lab = r.model.data["sa3d_label"]
    # Step 1 at labels 0: d/dlabel = -sum_obj aT + 0.3 sum_bg aT < 0 for A and for B.
    # Step 2: Adam keeps moving both up; C never moves.
    assert lab[0] > 1.0 and lab[1] > 1.0 and lab[2] == 0.0
    # The COB-GS loss (lambda = 1) would push B down instead: the 0.3 weight matters.
    from cobgs.refine.scores import mask_loss as ml, render_label_mask as rlm

    px = pixel_labels_from_mask(mask, 32, 32)
    x = torch.zeros(3, requires_grad=True)
    ml(rlm(model, view.camera, x, px).image[..., 0], px, 1.0).backward()
    assert x.grad[1] > 0
    # Recorded loss = mean of the two unnormalised losses: 0 at labels 0, then at [1, 1, 0].
    m1 = rlm(model, view.camera, torch.tensor([1.0, 1.0, 0.0]), px).image[..., 0]
    expected = 0.5 * float(-(m1 * (px == 1)).sum() + 0.3 * (m1 * (px == 0)).sum())
    assert r.stages[0].mean_loss == pytest.approx(expected, rel=1e-5)


def test_nosplit_is_table5_first_row():
    cfg = nosplit_config(RefineConfig(delta=0.4))
    assert (cfg.bags, cfg.bgtr, cfg.raem, cfg.delta) == (False, False, "off", 0.4)
    model, views, extent = tiny_scene(n_views=2)
    r = run_method("nosplit", model, views, masks_for(views, "ball"), extent,
                   config=RefineConfig(mask_stages=2, stage_length_views=1), progress=False, object_name="ball")
    assert r.method == "nosplit" and len(r.model) == len(model)
    # as long as the released labels-only run: COB-GS's 2 mask + 1 texture stages -> 3 mask stages
    assert [s.kind for s in r.stages] == ["mask", "mask", "mask"] and sum(s.split for s in r.stages) == 0
    # the defaults: forward 6 + 5 -> 11 stages of 2V = 22V iterations; 360: 4 + 3 -> 7 (14V)
    assert nosplit_config(RefineConfig()).num_mask_stages == 11
    assert nosplit_config(RefineConfig(scene_type="360")).num_mask_stages == 7


def test_run_method_dispatch_and_errors():
    model, views, extent = tiny_scene(n_views=2)
    masks = masks_for(views, "ball")
    results = {m: run_method(m, model, views, masks, extent, progress=False, object_name="ball",
                             config=RefineConfig(mask_stages=1, stage_length_views=1)
                             if m in ("cobgs", "nosplit") else None)
               for m in ("cobgs", "nosplit", "sa3d", "flashsplat")}
    for m, r in results.items():
        assert r.method == m and r.object_name == "ball"
        assert r.foreground.shape == r.background.shape == r.mask_values.shape == (len(r.model),)
        assert r.wall_s > 0
    with pytest.raises(InputError, match="unknown method"):
        run_method("saga", model, views, masks, extent)
    with pytest.raises(InputError, match="takes a"):
        run_method("sa3d", model, views, masks, extent, config=RefineConfig())
    with pytest.raises(InputError):
        run_flashsplat(model, views, masks[:1])


def test_make_config():
    from cobgs.refine.methods import make_config

    assert make_config("sa3d", {"lr": 0.5}) == SA3DConfig(lr=0.5)
    assert make_config("cobgs", {"raem": "paper", "delta": 0.6}) == RefineConfig(raem="paper", delta=0.6)
    assert make_config("flashsplat") == FlashSplatConfig()
    with pytest.raises(InputError, match="unknown"):
        make_config("sa3d", {"learning_rate": 1.0})
    with pytest.raises(InputError, match="unknown method"):
        make_config("saga")


def _weights_by_autograd(model, views, masks):
    """Each Gaussian's Σ α·T over a mask's pixels and over all pixels, by differentiating the
    rendered value channel with respect to per-Gaussian values (independent of label_votes)."""
    from cobgs.render.image import render

    obj = torch.zeros(len(model), dtype=torch.float64)
    tot = torch.zeros(len(model), dtype=torch.float64)
    for v, m in zip(views, masks):
        vals = torch.zeros(len(model), 1, requires_grad=True)
        img = render(model, v.camera, None, features=vals).image[..., 0]
        g_obj, = torch.autograd.grad(img[m].sum(), vals, retain_graph=True)
        g_all, = torch.autograd.grad(img.sum(), vals)
        obj += g_obj[:, 0].double()
        tot += g_all[:, 0].double()
    return obj, tot


def test_ludvig_uplifts_masks_as_weighted_means_and_prunes_as_released():
    """LUDVIG (naver/ludvig utils/solver.py uplifting): a Gaussian's feature is its α·T-weighted mean
    of the mask over every pixel of every view (checked against the renderer's own gradients); a
    scene above prune_min_gaussians loses the Gaussians at or below the weight quantile."""
    from cobgs.configs import LUDVIGConfig
    from cobgs.refine.ludvig import run_ludvig, uplift_masks

    model, view = three_gaussians()
    mask = view.masks["obj"].clone()
    mask[:, 14:] = False  # B mostly background now
    feat, weight = uplift_masks(model, [view, view], [mask, None])
    obj, tot = _weights_by_autograd(model, [view], [mask])
    assert torch.allclose(weight.double(), tot, rtol=1e-5, atol=1e-9)
    assert torch.allclose(feat.double(), obj / (tot + 1e-8), rtol=1e-5, atol=1e-7)
    assert feat[0] == pytest.approx(1.0, abs=1e-5) and 0.0 < float(feat[1]) < 0.5 and feat[2] == 0
    r = run_ludvig(model, [view], [mask], object_name="obj")
    assert r.method == "ludvig" and len(r.model) == 3 and torch.equal(r.mask_values, feat)
    assert r.mask_render == "scene_minmax" and r.mask_threshold == pytest.approx(0.25)
    assert r.foreground.tolist() == [True, float(feat[1]) / float(feat.max()) > 0.25, False]
    assert torch.equal(r.model.data["ludvig_feature"], feat)
    pruned = run_ludvig(model, [view], [mask], LUDVIGConfig(prune_min_gaussians=2))
    keep = weight > weight.median()  # (upstream: weights > quantile(0.5); of 3, only the heaviest stays)
    assert int(keep.sum()) == 1 and not keep[2]
    assert len(pruned.model) == 1 and pruned.stages[0].pruned == 2 and torch.equal(pruned.mask_values, feat[keep])
    assert len(run_ludvig(model, [view], [mask], LUDVIGConfig(prune_min_gaussians=3)).model) == 3  # (3 is not more)
    assert run_method("ludvig", model, [view], [mask], 1.0).method == "ludvig"
    with pytest.raises(InputError, match="at least one view with a mask"):
        run_ludvig(model, [view], [None])


def test_ludvig_is_evaluated_as_its_release_evaluates():
    """evaluation/spin_nvos: the feature rendered as the whole scene's colour on black, min-max
    normalised over the image, kept above 1 - k/100 (or Li's threshold); the segment stage's two
    masks are that render, and refine.json names the rule (only for such methods)."""
    from cobgs.configs import LUDVIGConfig
    from cobgs.refine.ludvig import li_threshold, minmax, run_ludvig
    from cobgs.refine.segment import render_object_mask, visible_object_mask
    from cobgs.render.image import render

    model, view = three_gaussians()
    r = run_ludvig(model, [view], [view.masks["obj"]])
    img = render(r.model, view.camera, None, features=r.mask_values[:, None]).image[..., 0]
    norm = minmax(img)
    assert norm.min() == 0 and norm.max() == 1
    want = norm > 0.25
    assert want.any() and not want.all()
    assert torch.equal(render_object_mask(r, view.camera), want)
    assert torch.equal(visible_object_mask(r, view.camera), want)
    assert torch.equal(render_object_mask(r, view.camera, threshold=0.6), norm > 0.6)
    li = run_ludvig(model, [view], [view.masks["obj"]], LUDVIGConfig(thresholding="li"))
    assert li.mask_render == "scene_minmax_li" and li.mask_threshold is None
    assert torch.equal(render_object_mask(li, view.camera), norm > li_threshold(norm))
    assert r.summary()["mask_render"] == "scene_minmax"
    flash = run_flashsplat(model, [view], [view.masks["obj"]])
    assert "mask_render" not in flash.summary()
