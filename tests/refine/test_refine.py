"""COB-GS refinement: scores, splitting, stage invariants, RAEM, configuration."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from cobgs.errors import InputError
from cobgs.gaussians.model import GaussianModel, quat_to_rotmat
from cobgs.refine.alternation import Refiner, final_sets, masks_for, refine
from cobgs.configs import RefineConfig
from cobgs.refine.scores import (
    LABEL,
    ScoreAccumulator,
    ensure_label,
    mask_loss,
    pixel_labels_from_mask,
    render_label_mask,
    view_scores,
)
from cobgs.refine.split import boundary_split, pixel_footprint, raem_prune_mask, split_candidates
from refine_fixtures import three_gaussians, tiny_scene

CORE_NO_LABEL = ("means", "log_scales", "quats", "opacity_logits", "sh0", "shN")


# -- scores ---------------------------------------------------------------------------------
def test_view_scores_from_known_counts():
    # Rows: (N-, N+). Expected r = |N+ - N-| / (N+ + N- + 1e-6), unseen -> 1.
    counts = torch.tensor([[0, 10], [5, 5], [0, 0], [3, 1], [7, 0]], dtype=torch.int32)
    r = view_scores(counts)
    expected = torch.tensor([10 / (10 + 1e-6), 0.0, 1.0, 2 / (4 + 1e-6), 7 / (7 + 1e-6)])
    assert torch.allclose(r, expected, atol=1e-7)


def test_view_scores_weighted_variant_and_lambda_zero():
    counts = torch.tensor([[2, 2], [0, 0], [4, 0]], dtype=torch.int32)
    weights = torch.tensor([[0.1, 0.3], [0.0, 0.0], [0.5, 0.0]])
    r = view_scores(counts, weights, use_weights=True)
    assert torch.allclose(r, torch.tensor([0.2 / 0.4, 1.0, 1.0]), atol=1e-5)
    # The count variant sees the first Gaussian as perfectly ambiguous instead.
    assert view_scores(counts)[0] == 0.0
    # lambda = 0: background pixels carry no gradient, so N- = 0 and a Gaussian seen only
    # by background pixels has no signal at all (unseen -> 1).
    r0 = view_scores(counts, lam=0.0)
    assert torch.allclose(r0, torch.tensor([2 / (2 + 1e-6), 1.0, 1.0]), atol=1e-6)
    with pytest.raises(InputError):
        view_scores(counts, None, use_weights=True)


def test_score_accumulator_stage_mean():
    acc = ScoreAccumulator(3)
    for s in ([1.0, 0.0, 0.5], [1.0, 0.2, 0.5], [1.0, 0.4, 1.0], [1.0, 0.2, 0.0]):
        acc.add(torch.tensor(s))
    assert torch.allclose(acc.mean(), torch.tensor([1.0, 0.2, 0.5]))
    assert torch.equal(acc.ambiguous(0.5), torch.tensor([False, True, False]))
    # Divided by the stage length when given (released: base_num = 2V).
    assert torch.allclose(acc.mean(8), torch.tensor([0.5, 0.1, 0.25]))
    with pytest.raises(InputError):
        acc.add(torch.zeros(4))
    acc.reset(2)
    with pytest.raises(InputError):
        acc.mean()


def test_hand_built_counts_and_scores():
    model, view = three_gaussians()
    labels = pixel_labels_from_mask(view.masks["obj"], 32, 32)
    ensure_label(model)
    out = render_label_mask(model, view.camera, torch.sigmoid(model.data[LABEL]), labels)
    n_neg, n_pos = out.label_counts[:, 0].tolist(), out.label_counts[:, 1].tolist()
    # A lies entirely in the object half: only N+.
    assert n_pos[0] > 0 and n_neg[0] == 0
    # B sits on the mask edge (x = 16 px), mirror-symmetric: N+ = N-.
    assert n_pos[1] == n_neg[1] > 0
    # C is behind the camera: nothing.
    assert n_pos[2] == n_neg[2] == 0
    # The same counts from the pure-PyTorch reference rasterizer.
    ref = render_label_mask(model, view.camera, torch.sigmoid(model.data[LABEL]), labels, backend="reference")
    assert torch.equal(ref.label_counts, out.label_counts)
    r = view_scores(out.label_counts)
    assert r[0] == pytest.approx(1.0, abs=1e-6) and r[1] == 0.0 and r[2] == 1.0


def test_refiner_accumulates_rasterizer_scores_and_ignores_dont_care_pixels():
    model, view = three_gaussians()
    mask = view.masks["obj"].to(torch.int64)
    mask[:, 16:] = -1  # the right half is "don't care": B now sees only object pixels
    r = Refiner(model, [view], [mask], 1.0, RefineConfig(stage_length_views=3))
    for _ in range(3):
        r.mask_step(0)
    mean = r.scores.mean()
    assert r.scores.iterations == 3
    assert torch.allclose(mean, torch.ones(3), atol=1e-6)  # A, B unambiguous; C unseen


def test_mask_loss_normalised_and_gradient_sign():
    M = torch.full((4, 5), 0.5, requires_grad=True)
    G = torch.zeros(4, 5, dtype=torch.int32)
    G[:, :2] = 1
    G[0, 4] = -1
    loss = mask_loss(M, G)
    assert loss.item() == pytest.approx((-8 * 0.5 + 11 * 0.5) / 20)
    loss.backward()
    assert torch.all(M.grad[G == 1] == -1 / 20) and torch.all(M.grad[G == 0] == 1 / 20)
    assert M.grad[0, 4] == 0


def test_mask_path_reaches_labels_only():
    model, view = three_gaussians()
    ensure_label(model)
    labels = pixel_labels_from_mask(view.masks["obj"], 32, 32)
    out = render_label_mask(model, view.camera, torch.sigmoid(model.data[LABEL]), labels)
    mask_loss(out.image[..., 0], labels).backward()
    assert model.data[LABEL].grad is not None and model.data[LABEL].grad.abs().sum() > 0
    for k in CORE_NO_LABEL:
        assert model.data[k].grad is None


def test_pixel_labels_validation():
    assert torch.equal(pixel_labels_from_mask(None, 2, 3), torch.full((2, 3), -1, dtype=torch.int32))
    with pytest.raises(InputError, match="shape"):
        pixel_labels_from_mask(torch.zeros(3, 3, dtype=torch.bool), 2, 3)
    with pytest.raises(InputError, match="bool or integer"):
        pixel_labels_from_mask(torch.zeros(2, 3), 2, 3)
    with pytest.raises(InputError, match="values"):
        pixel_labels_from_mask(torch.full((2, 3), 2), 2, 3)


# -- splitting ------------------------------------------------------------------------------
def _model_with_label(n_big: int, n_small: int, seed: int = 0) -> GaussianModel:
    g = torch.Generator().manual_seed(seed)
    n = n_big + n_small
    scales = torch.cat([torch.tensor([[0.2, 0.05, 0.01]]).repeat(n_big, 1),
                        torch.full((n_small, 3), 0.001)])
    q = torch.nn.functional.normalize(torch.tensor([[0.9, 0.3, -0.2, 0.25]]), dim=-1).repeat(n, 1)
    m = GaussianModel(torch.randn(n, 3, generator=g), torch.log(scales), q, torch.randn(n, generator=g),
                      torch.randn(n, 1, 3, generator=g), torch.randn(n, 3, 3, generator=g))
    m.add_extra(LABEL, torch.randn(n, generator=g), fill=0.0)
    m.add_extra("object_id", torch.arange(n), fill=0)
    return m


def test_boundary_split_mechanics_and_optimizer_states():
    m = _model_with_label(n_big=6, n_small=4)
    n = len(m)
    label_opt = m.make_adam({LABEL: 0.1})
    tex_opt = m.make_adam({"means": 1e-3, "sh0": 1e-3, "shN": 1e-3, "opacity_logits": 1e-3,
                           "log_scales": 1e-3, "quats": 1e-3})
    # One optimizer step so every moment is non-zero.
    loss = sum(t.sum() for t in m.data.values() if t.is_floating_point())
    loss.backward()
    label_opt.step()
    tex_opt.step()
    before = {k: v.detach().clone() for k, v in m.data.items()}
    moments = {k: label_opt.state[m.data[k]]["exp_avg"].clone() if k == LABEL
               else tex_opt.state[m.data[k]]["exp_avg"].clone() for k in m.data if m.data[k].is_floating_point()}
    ambiguous = torch.tensor([True, True, False, True, False, False, True, True, False, False])
    extent = 2.0  # split threshold 0.02: the big ones (max 0.2) split, the small (0.001) do not
    assert torch.equal(split_candidates(m, ambiguous, extent),
                       ambiguous & torch.tensor([True] * 6 + [False] * 4))
    n_split = boundary_split(m, ambiguous, extent, reset=(LABEL,), optimizers=[label_opt, tex_opt],
                             generator=torch.Generator().manual_seed(1))
    parents = torch.tensor([0, 1, 3])
    assert n_split == 3
    assert len(m) == n - 3 + 6
    kept = torch.tensor([i for i in range(n) if i not in parents.tolist()])
    for k, v in m.data.items():
        assert v.shape[0] == len(m)
        assert torch.equal(v.detach()[: len(kept)], before[k][kept])  # kept rows untouched
    kids = slice(len(kept), len(m))
    par2 = parents.repeat(2)  # children are child-major: all first children, then all second
    assert torch.allclose(m.scales[kids], torch.exp(before["log_scales"][par2]) / 1.6)
    for k in ("quats", "opacity_logits", "sh0", "shN", "object_id"):
        assert torch.equal(m.data[k].detach()[kids], before[k][par2])
    assert torch.all(m.data[LABEL][kids] == 0)  # label logit reset
    assert not torch.equal(m.means[kids], before["means"][par2])  # positions resampled
    for k, mom in moments.items():
        opt = label_opt if k == LABEL else tex_opt
        st = opt.state[m.data[k]]
        assert st["exp_avg"].shape == m.data[k].shape and st["exp_avg_sq"].shape == m.data[k].shape
        assert torch.equal(st["exp_avg"][: len(kept)], mom[kept])
        assert torch.all(st["exp_avg"][kids] == 0) and torch.all(st["exp_avg_sq"][kids] == 0)


def test_split_children_positions_follow_parent_covariance():
    # Many identical anisotropic, rotated parents: the child offsets must have covariance
    # R diag(s^2) R^T (a sample of the parent Gaussian).
    n = 4000
    m = _model_with_label(n_big=n, n_small=0)
    with torch.no_grad():
        m.data["means"].zero_()
    s = torch.tensor([0.2, 0.05, 0.01])
    R = quat_to_rotmat(m.quats[:1].detach())[0]
    boundary_split(m, torch.ones(n, dtype=torch.bool), 1.0, reset=(LABEL,), generator=torch.Generator().manual_seed(0))
    x = m.means.detach().double()
    assert len(m) == 2 * n
    cov = x.T @ x / len(x)
    expected = (R.double() @ torch.diag(s.double() ** 2) @ R.T.double())
    # 8000 samples: relative standard error of a variance ~ sqrt(2/8000) = 1.6 %.
    assert torch.allclose(cov, expected, atol=0.06 * float(s[0] ** 2))
    assert x.mean(0).abs().max() < 4 * 0.2 / math.sqrt(2 * n)


# -- stage invariants -----------------------------------------------------------------------
def _snapshot(m, names):
    return {k: m.data[k].detach().clone() for k in names}


def test_mask_stage_keeps_geometry_and_colour_bit_identical():
    model, views, extent = tiny_scene(n_views=3)
    cfg = RefineConfig(bags=False, stage_length_views=2)
    r = Refiner(model, views, masks_for(views, "ball"), extent, cfg)
    geo = _snapshot(model, CORE_NO_LABEL)
    lab0 = model.data[LABEL].detach().clone()
    for _ in range(cfg.stage_length(3)):
        r.mask_step(r.next_view())
    info = r.end_mask_stage(cfg.stage_length(3), last=False)
    assert info["split"] == 0
    for k, v in geo.items():
        assert torch.equal(model.data[k].detach(), v), k
    assert not torch.equal(model.data[LABEL].detach(), lab0)  # labels did train


def test_mask_stage_with_split_keeps_unsplit_gaussians_identical():
    model, views, extent = tiny_scene(n_views=3)
    cfg = RefineConfig(stage_length_views=2, split_size_fraction=0.0, split_object_share=0.0)  # (Eq. 6's set alone)
    r = Refiner(model, views, masks_for(views, "ball"), extent, cfg)
    geo = _snapshot(model, CORE_NO_LABEL)
    for _ in range(cfg.stage_length(3)):
        r.mask_step(r.next_view())
    amb = r.scores.ambiguous(cfg.threshold, cfg.stage_length(3))
    info = r.end_mask_stage(cfg.stage_length(3), last=False)
    assert info["split"] == int(amb.sum()) > 0
    keep = ~amb
    for k, v in geo.items():
        assert torch.equal(model.data[k].detach()[: int(keep.sum())], v[keep]), k
    assert r.scores.iterations == 0 and r.scores.sum.shape == (len(model),)  # reset after the split


def test_texture_stage_keeps_labels_bit_identical():
    model, views, extent = tiny_scene(n_views=3)
    cfg = RefineConfig(bags=False)
    r = Refiner(model, views, masks_for(views, "ball"), extent, cfg)
    for _ in range(6):
        r.mask_step(r.next_view())
    labels = model.data[LABEL].detach().clone()
    geo = _snapshot(model, CORE_NO_LABEL)
    # Perturb the colours so the texture loss has work to do.
    with torch.no_grad():
        model.data["sh0"].add_(0.3)
    for _ in range(6):
        r.texture_step(r.next_view())
    assert torch.equal(model.data[LABEL].detach(), labels)
    assert not torch.equal(model.data["sh0"].detach(), geo["sh0"] + 0.3)
    assert not torch.equal(model.data["means"].detach(), geo["means"])


def test_texture_stage_learning_rates():
    model, views, extent = tiny_scene(n_views=2)
    r = Refiner(model, views, masks_for(views, "ball"), extent, RefineConfig())
    lrs = {g["name"]: g["lr"] for g in r.texture_opt.param_groups}
    assert lrs["means"] == pytest.approx(1.6e-6 * extent)
    assert lrs == pytest.approx({"means": 1.6e-6 * extent, "sh0": 2.5e-3, "shN": 2.5e-3 / 20, "opacity_logits": 0.025,
                                 "log_scales": 5e-3, "quats": 1e-3})
    assert [g["lr"] for g in r.label_opt.param_groups] == [0.1]
    assert r.label_opt.defaults["eps"] == 1e-15 and r.texture_opt.defaults["eps"] == 1e-15


def test_view_order_without_replacement():
    model, views, extent = tiny_scene(n_views=4)
    r = Refiner(model, views, masks_for(views, "ball"), extent, RefineConfig(seed=3))
    draws = [r.next_view() for _ in range(12)]
    for k in range(3):
        assert sorted(draws[4 * k: 4 * k + 4]) == [0, 1, 2, 3]


# -- schedules and the whole run ------------------------------------------------------------
def test_schedule_defaults():
    f, s = RefineConfig(), RefineConfig(scene_type="360")
    assert f.threshold == 0.5 and s.threshold == 0.8
    assert f.plan() == ["mask", "texture"] * 5 + ["mask"]
    assert s.plan() == ["mask", "texture"] * 3 + ["mask"]
    assert len(f.plan()) * f.stage_length(10) == 22 * 10
    assert len(s.plan()) * s.stage_length(10) == 14 * 10
    assert RefineConfig(bgtr=False).plan() == ["mask"] * 6
    assert RefineConfig(delta=0.3, scene_type="360").threshold == 0.3


@pytest.mark.parametrize("kw", [dict(scene_type="llff"), dict(raem="yes"), dict(score="alpha"), dict(delta=1.5),
                                dict(mask_stages=0), dict(stage_length_views=0), dict(mask_lambda=-1.0),
                                dict(texture_adam="warm")])
def test_config_validation(kw):
    with pytest.raises(InputError):
        RefineConfig(**kw)


def test_refine_run_statistics_and_determinism():
    model, views, extent = tiny_scene(n_views=3)
    cfg = RefineConfig(mask_stages=3, stage_length_views=2, raem="released")  # prunes every ambiguous one
    n0 = len(model)
    a = refine(model, views, masks_for(views, "ball"), extent, cfg, object_name="ball", progress=False)
    assert len(model) == n0 and LABEL not in model.data  # input untouched
    kinds = [s.kind for s in a.stages]
    assert kinds == ["mask", "texture", "mask", "texture", "mask"]
    assert all(s.iterations == 6 for s in a.stages)
    for s0, s1 in zip(a.stages, a.stages[1:]):
        assert s1.gaussians_start == s0.gaussians_end
    masks_ = [s for s in a.stages if s.kind == "mask"]
    assert all(s.ambiguous >= s.ambiguous_large >= s.split for s in masks_[:-1])
    assert masks_[-1].split == 0 and masks_[-1].pruned == masks_[-1].ambiguous == a.ambiguous_final
    assert a.num_gaussians_end == len(a.model) == n0 + sum(s.split for s in masks_) - masks_[-1].pruned
    assert len(a.stage_scores) == 3 and a.stage_scores[-1].shape[0] == masks_[-1].gaussians_start
    assert a.foreground.shape == (len(a.model),) and not bool((a.foreground & a.background).any())
    assert torch.equal(a.foreground, a.mask_values > 0.9)
    b = refine(model, views, masks_for(views, "ball"), extent, cfg, object_name="ball", progress=False)
    for k in a.model.data:
        assert torch.equal(a.model.data[k].detach(), b.model.data[k].detach()), k
    s = a.summary()
    assert s["splits"] == sum(x.split for x in a.stages) and s["config"]["threshold"] == 0.5


def test_ablation_switches():
    model, views, extent = tiny_scene(n_views=3)
    base = RefineConfig(mask_stages=2, stage_length_views=2)
    none = refine(model, views, masks_for(views, "ball"), extent,
                  dataclasses.replace(base, bags=False, bgtr=False, raem="off"), progress=False)
    assert [s.kind for s in none.stages] == ["mask", "mask"]
    assert len(none.model) == len(model) and sum(s.split + s.pruned for s in none.stages) == 0
    for k in CORE_NO_LABEL:
        assert torch.equal(none.model.data[k].detach(), model.data[k].detach())
    bags = refine(model, views, masks_for(views, "ball"), extent,
                  dataclasses.replace(base, bgtr=False, raem="off", split_size_fraction=0.0), progress=False)
    assert bags.stages[0].split > 0 and bags.stages[-1].pruned == 0


def test_raem_variants():
    model, view = three_gaussians()
    amb = torch.tensor([True, True, False])
    assert not raem_prune_mask(model, amb, "off").any()
    assert torch.equal(raem_prune_mask(model, amb, "released"), amb)
    # Footprints: A 0.02 * 50 / 2 = 0.5 px, B 0.05 * 50 / 2 = 1.25 px, C unseen = 0.
    fp = pixel_footprint(model, [view.camera])
    assert torch.allclose(fp, torch.tensor([0.5, 1.25, 0.0]))
    assert torch.equal(raem_prune_mask(model, amb, "paper", [view.camera]), torch.tensor([True, False, False]))
    assert torch.equal(raem_prune_mask(model, amb, "paper", [view.camera], footprint_px=2.0), amb)
    with pytest.raises(InputError):
        raem_prune_mask(model, amb, "paper")


def test_refine_input_errors():
    model, views, extent = tiny_scene(n_views=2)
    with pytest.raises(InputError, match="masks"):
        refine(model, views, [None], extent, progress=False)
    with pytest.raises(InputError, match="annotated"):
        refine(model, views, [None, None], extent, progress=False)
    with pytest.raises(InputError, match="extent"):
        refine(model, views, masks_for(views, "ball"), -1.0, progress=False)
    with pytest.raises(InputError):
        refine(model, [], [], extent, progress=False)


@pytest.mark.parametrize("variant", ["released", "paper"])
def test_apply_raem_matches_running_with_raem(variant):
    from cobgs.refine.alternation import apply_raem

    model, views, extent = tiny_scene(n_views=3)
    base = RefineConfig(mask_stages=2, stage_length_views=2, raem_footprint_px=2.0)
    off = refine(model, views, masks_for(views, "ball"), extent, dataclasses.replace(base, raem="off"),
                 progress=False)
    direct = refine(model, views, masks_for(views, "ball"), extent, dataclasses.replace(base, raem=variant),
                    progress=False)
    post = apply_raem(off, variant, views)
    assert direct.stages[-1].pruned > 0
    assert post.stages[-1].pruned == direct.stages[-1].pruned and len(post.model) == len(direct.model)
    for k in direct.model.data:
        assert torch.equal(post.model.data[k].detach(), direct.model.data[k].detach()), k
    assert torch.equal(post.foreground, direct.foreground) and post.config["raem"] == variant
    assert off.stages[-1].pruned == 0 and len(off.model) > len(post.model)  # input untouched
    with pytest.raises(InputError):
        apply_raem(direct, "paper", views)
    # spare: those Gaussians stay whatever RAEM says; the others go as before
    pruned = ~post.raem_keep
    spare = torch.zeros(len(off.model), dtype=torch.bool)
    spare[torch.nonzero(pruned)[0]] = True
    kept = apply_raem(off, variant, views, spare=spare)
    assert kept.stages[-1].pruned == post.stages[-1].pruned - 1 and len(kept.model) == len(post.model) + 1
    assert torch.equal(~kept.raem_keep, pruned & ~spare)
    # RefineConfig.raem_spare_object: the run spares what the labels call object, as apply_raem does
    # with spare = the labels' foreground
    from cobgs.configs import LABEL, key_without_later
    from cobgs.refine.alternation import label_sets

    long = dataclasses.replace(base, stage_length_views=8)  # 24-iteration stages: labels pass 0.9
    off = refine(model, views, masks_for(views, "ball"), extent, dataclasses.replace(long, raem="off"), progress=False)
    spared = refine(model, views, masks_for(views, "ball"), extent,
                    dataclasses.replace(long, raem=variant, raem_spare_object=True), progress=False)
    fg = label_sets(off.model.data[LABEL])[0]
    assert (fg & ~apply_raem(off, variant, views).raem_keep).any()  # RAEM as published prunes some of them
    again = apply_raem(off, variant, views, spare=fg)
    assert len(spared.model) == len(again.model) and torch.equal(spared.raem_keep, again.raem_keep)
    assert not (fg & ~spared.raem_keep).any() and not spared.raem_keep.all()
    assert "raem_spare_object" not in key_without_later(RefineConfig, RefineConfig().as_dict())
    assert "raem_spare_object" not in key_without_later(RefineConfig, RefineConfig(raem="off", raem_spare_object=True).as_dict())
    assert key_without_later(RefineConfig, RefineConfig(raem_spare_object=True).as_dict())["raem_spare_object"] is True
    # RefineConfig.raem_object_by_masks: of the two (as published, spared), the one whose object
    # alone agrees better with the training masks after the check; what bm_raem's object_set picks
    from cobgs.refine.consistency import drawn_agreement
    from cobgs.refine.scores import pixel_labels_from_mask

    chosen = refine(model, views, masks_for(views, "ball"), extent,
                    dataclasses.replace(long, raem=variant, raem_object_by_masks=True), progress=False)
    masks = masks_for(views, "ball")
    px = [pixel_labels_from_mask(mk, v.height, v.width) for v, mk in zip(views, masks) if mk is not None]
    seen = [v for v, mk in zip(views, masks) if mk is not None]
    cfg = dataclasses.replace(long, raem=variant)
    agree = {}
    for name, res in (("paper", apply_raem(off, variant, views)), ("spare", again)):
        kept = final_sets(res.model, seen, px, cfg)[0]
        agree[name] = drawn_agreement(res.model, kept, seen, px)
    want = "spare" if agree["spare"] > agree["paper"] else "paper"
    assert chosen.config["raem_object_chose"] == want
    ref = again if want == "spare" else apply_raem(off, variant, views)
    assert len(chosen.model) == len(ref.model) and torch.equal(chosen.raem_keep, ref.raem_keep)
    assert chosen.stages[-1].pruned == int((~ref.raem_keep).sum()) and chosen.stages[-1].gaussians_end == len(ref.model)
    for k in ref.model.data:
        assert torch.equal(chosen.model.data[k].detach(), ref.model.data[k].detach()), k
    assert "raem_object_by_masks" not in key_without_later(RefineConfig, RefineConfig().as_dict())
    assert "raem_object_by_masks" not in key_without_later(
        RefineConfig, RefineConfig(raem="off", raem_object_by_masks=True).as_dict())
    with pytest.raises(InputError, match="raem_object_by_masks and raem_spare_object are both on"):
        RefineConfig(raem_object_by_masks=True, raem_spare_object=True)


def test_peak_memory_sees_an_allocation_after_a_free():
    from cobgs.refine.result import PeakMemory

    big = torch.ones(40_000_000)  # 160 MB allocated and freed: stays in the process
    del big
    with PeakMemory() as mem:
        x = torch.ones(25_000_000)  # 100 MB
        x += 1
    assert 80 * 2**20 < mem.peak_bytes < 400 * 2**20


def test_final_scores_are_full_stage_means_over_split_children():
    """RAEM decides on the last MASK stage's scores: every Gaussian there — split children
    included — must have a full stage of per-view scores (accumulator reset at the split,
    not carried over, divided by the stage length), with "unseen" adding 1 per view."""
    model, view = three_gaussians()
    masks = [view.masks["obj"]]
    # One view, 3 iterations per stage, no texture stage: geometry is fixed, so each
    # Gaussian's stage mean must equal its single-view score exactly.
    cfg = RefineConfig(mask_stages=2, stage_length_views=3, bgtr=False, raem="off", split_size_fraction=0.0,
                       delta=0.5)
    r = refine(model, [view], masks, 10.0, cfg, progress=False)
    first, last = [s for s in r.stages if s.kind == "mask"]
    assert first.split == 1  # B (score ~0) is split; A (inside) and C (unseen) are not
    assert len(r.model) == 4 and r.stage_scores[-1].shape == (4,)
    out = render_label_mask(r.model, view.camera, torch.sigmoid(r.model.data[LABEL].detach()),
                            pixel_labels_from_mask(masks[0], view.height, view.width))
    expect = view_scores(out.label_counts)
    assert torch.allclose(r.stage_scores[-1], expect, atol=1e-6)
    # A and C are the first two rows (kept), the children follow; C is unseen: exactly 1.
    assert r.stage_scores[-1][0] == pytest.approx(1.0) and r.stage_scores[-1][1] == 1.0
    assert last.ambiguous == int((expect < 0.5).sum())


def test_scene_before_raem_is_the_run_without_raem():
    """RAEM is the last edit: the pruned Gaussians put back at their indices give exactly
    the scene of the same run with RAEM off (paper Table 4 measures texture there)."""
    from cobgs.refine.result import restore_pruned

    model, views, extent = tiny_scene(n_views=4)
    masks = masks_for(views, "ball")
    cfg = RefineConfig(mask_stages=2, stage_length_views=1.0, delta=0.6, raem="released")
    on = refine(model, views, masks, extent, cfg, progress=False)
    off = refine(model, views, masks, extent, dataclasses.replace(cfg, raem="off"), progress=False)
    pruned = on.stages[-1].pruned
    assert pruned > 0 and on.summary()["raem_pruned"] == pruned and off.raem_keep is None
    before = on.model_before_raem()
    assert len(before) == len(off.model) == len(on.model) + pruned
    for k in off.model.data:
        assert torch.equal(before.data[k], off.model.data[k]), k
    assert off.model_before_raem() is off.model  # nothing pruned: the model itself
    # apply_raem records the same pieces
    from cobgs.refine.alternation import apply_raem

    again = apply_raem(off, "released", views)
    assert torch.equal(again.raem_keep, on.raem_keep)
    with pytest.raises(InputError, match="restore"):
        restore_pruned(on.model, on.raem_keep[1:], on.raem_removed)


def _check_scene():
    """32x32 camera at the origin (f = 50); the mask is the left half. Gaussian 0 (A) sits in
    the object (column ~8); 1..81 are a dense 9x9 patch outside it (columns ~20-28, B = 41 its
    centre); the last one is an opaque background wall in front of the patch."""
    import torch

    from cobgs.data.scene import View
    from cobgs.render.camera import Camera
    from cobgs.gaussians.model import GaussianModel

    cam = Camera(K=torch.tensor([[50.0, 0, 16.0], [0, 50.0, 16.0], [0, 0, 1]]), viewmat=torch.eye(4),
                 width=32, height=32, name="cam")
    g = torch.arange(-4, 5, dtype=torch.float32) * 0.04
    yy, xx = torch.meshgrid(g, g, indexing="ij")
    patch = torch.stack([0.3 + xx.flatten(), yy.flatten(), torch.full((81,), 2.0)], 1)
    means = torch.cat([torch.tensor([[-0.3, 0.0, 2.0]]), patch, torch.tensor([[0.3, 0.0, 1.0]])])
    scales = torch.cat([torch.full((82, 3), 0.05), torch.full((1, 3), 0.4)])
    n = len(means)
    model = GaussianModel(means, scales.log(), torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), torch.full((n,), 4.0),
                          torch.zeros(n, 1, 3), torch.zeros(n, 0, 3))
    mask = torch.zeros(32, 32, dtype=torch.bool)
    mask[:, :16] = True
    return model, View(camera=cam, image=torch.zeros(32, 32, 3), name="cam", masks={"obj": mask})


def test_object_render_check_drops_what_falls_outside_the_object_alone():
    """docs/method.md §7: the foreground rendered alone; what lies on background pixels where
    nothing hides it leaves the foreground; what the masks cannot judge keeps its verdict."""
    import torch

    from cobgs.refine.consistency import object_render_check
    from cobgs.refine.scores import pixel_labels_from_mask

    model, view = _check_scene()
    n, B = len(model), 41
    px = [pixel_labels_from_mask(view.masks["obj"], 32, 32)]
    fg = torch.ones(n, dtype=torch.bool)
    fg[-1] = False
    # without the wall the patch is in plain sight on background pixels: all of it leaves
    no_wall = model.select(torch.arange(n - 1))
    kept = object_render_check(no_wall, fg[:-1], [view], px)
    assert kept[0] and not kept[1:].any()
    # behind the wall the patch is hidden in the scene render: where the object alone covers
    # it, the masks say nothing; B (its centre) casts no vote there and keeps its verdict; the
    # patch's rim still votes with its tails outside the object's alone render
    kept = object_render_check(model, fg, [view], px)
    assert kept[0] and kept[B] and not kept[-1]
    assert not kept[1:-1].all()
    # the check only removes, and an empty foreground stays empty
    assert not (kept & ~fg).any()
    assert not object_render_check(model, torch.zeros(n, dtype=torch.bool), [view], px).any()


def test_the_check_leaves_the_mask_edges_out_when_asked():
    """Issue 59 item 2 candidate (RefineConfig.object_check_edge_px): pixels within r of a mask
    edge cast no vote in the object-render check. A Gaussian on the background side of the edge,
    within r, is removed by the plain check and keeps its verdict with the band; one far from the
    edge is judged as before; the band is the pixels within r of both labels, never ignored ones."""
    import torch

    from cobgs.refine.consistency import edge_band, object_render_check
    from cobgs.refine.scores import pixel_labels_from_mask
    from cobgs.configs import RefineConfig, key_without_later

    lab = torch.full((6, 8), 0, dtype=torch.int32)
    lab[:, :4] = 1
    lab[0, :] = -1
    band = edge_band(lab, 1)
    assert band[1:, 3:5].all() and not band[1:, :3].any() and not band[1:, 5:].any() and not band[0].any()
    assert not edge_band(lab, 0).any() and edge_band(lab, 2)[1:, 2:6].all()

    model, view = _check_scene()
    model = model.select(torch.arange(len(model) - 1))  # (no wall)
    px = [pixel_labels_from_mask(view.masks["obj"], 32, 32)]
    n = len(model)
    fg = torch.ones(n, dtype=torch.bool)
    plain = object_render_check(model, fg, [view], px)
    wide = object_render_check(model, fg, [view], px, edge_px=12)  # the patch (columns ~20-28) in the band
    narrow = object_render_check(model, fg, [view], px, edge_px=2)
    assert plain[0] and not plain[1:].any()
    assert wide[0] and wide[1:].sum() > 0 and not (wide & ~fg).any()
    assert torch.equal(narrow, plain)  # the patch lies well outside a 2-pixel band: judged as before
    assert "object_check_edge_px" not in key_without_later(RefineConfig, RefineConfig().as_dict())


def test_the_iou_rule_of_the_check_keeps_what_draws_a_thin_object():
    """Issue 59 item 2 (RefineConfig.object_check_rule = "iou"): a Gaussian leaves the checked
    foreground only when the object's render agrees better with the masks without it (soft IoU
    Σa / (M + Σb)). A pole drawn by one Gaussian with most of its weight beside the pole is
    removed by the votes rule (a < b) and kept by the IoU rule; a Gaussian wholly on background
    pixels leaves under both; the rule never removes what the votes rule keeps."""
    import torch

    from cobgs.configs import RefineConfig, key_without_later
    from cobgs.data.scene import View
    from cobgs.errors import InputError
    from cobgs.gaussians.model import GaussianModel
    from cobgs.refine.consistency import iou_keep, object_render_check
    from cobgs.refine.scores import pixel_labels_from_mask
    from cobgs.render.camera import Camera

    # the arithmetic: a well-drawn object (IoU 91 / 105) loses its stray Gaussian (1/3 < 0.87)
    assert iou_keep(torch.tensor([90.0, 1.0]), torch.tensor([2.0, 3.0]), 100.0).tolist() == [True, False]
    # a lone straddler (4 on the object, 6 beside it; IoU 4 / 16) stays: without it nothing is drawn
    assert iou_keep(torch.tensor([4.0]), torch.tensor([6.0]), 10.0).tolist() == [True]
    # rounds: removing c (1/30 < IoU 0.71) lifts the IoU to 0.895, past b's 0.85, which then goes
    keep = iou_keep(torch.tensor([90.0, 8.5, 1.0]), torch.tensor([0.0, 10.0, 30.0]), 100.0)
    assert keep.tolist() == [True, False, False]
    # the bar is min(λ, IoU): at λ = 0.5 the votes rule keeps b (6 > 0.5 · 10), and so does this one
    assert iou_keep(torch.tensor([90.0, 6.0]), torch.tensor([0.0, 10.0]), 90.0, mask_lambda=0.5).tolist() == [True, True]
    assert iou_keep(torch.tensor([90.0, 6.0]), torch.tensor([0.0, 10.0]), 90.0).tolist() == [True, False]

    cam = Camera(K=torch.tensor([[50.0, 0, 16.0], [0, 50.0, 16.0], [0, 0, 1]]), viewmat=torch.eye(4),
                 width=32, height=32, name="cam")
    # 0: a wide Gaussian over the pole (columns 14-17, σ ≈ 3.75 px); 1: one wholly beside it
    means = torch.tensor([[0.0, 0.0, 2.0], [0.36, 0.0, 2.0]])
    scales = torch.tensor([[0.15, 0.15, 0.15], [0.04, 0.04, 0.04]])
    model = GaussianModel(means, scales.log(), torch.tensor([[1.0, 0, 0, 0]]).repeat(2, 1), torch.full((2,), 4.0),
                          torch.zeros(2, 1, 3), torch.zeros(2, 0, 3))
    mask = torch.zeros(32, 32, dtype=torch.bool)
    mask[:, 14:18] = True
    view = View(camera=cam, image=torch.zeros(32, 32, 3), name="cam", masks={"pole": mask})
    px = [pixel_labels_from_mask(mask, 32, 32)]
    fg = torch.ones(2, dtype=torch.bool)
    votes = object_render_check(model, fg, [view], px)
    iou = object_render_check(model, fg, [view], px, rule="iou")
    assert votes.tolist() == [False, False] and iou.tolist() == [True, False]
    with pytest.raises(InputError, match="object check rule must be 'votes', 'iou' or 'removal', got 'vote'"):
        object_render_check(model, fg, [view], px, rule="vote")
    # on the check scene (a small Gaussian in the object, a patch beside it) both rules agree
    scene_model, scene_view = _check_scene()
    scene_model = scene_model.select(torch.arange(len(scene_model) - 1))
    spx = [pixel_labels_from_mask(scene_view.masks["obj"], 32, 32)]
    all_fg = torch.ones(len(scene_model), dtype=torch.bool)
    assert torch.equal(object_render_check(scene_model, all_fg, [scene_view], spx, rule="iou"),
                       object_render_check(scene_model, all_fg, [scene_view], spx))
    # the default since 2026-11-29; in the key unless it is the check as measured before it, or
    # the check is off (then the rule says nothing of the run, whatever it holds)
    assert RefineConfig().object_check_rule == "iou"
    assert key_without_later(RefineConfig, RefineConfig().as_dict())["object_check_rule"] == "iou"
    assert "object_check_rule" not in key_without_later(RefineConfig, RefineConfig(object_check_rule="votes").as_dict())
    off = RefineConfig(object_check="off").as_dict()
    assert "object_check_rule" not in key_without_later(RefineConfig, off)
    assert "object_check_rule" not in key_without_later(RefineConfig, RefineConfig().as_dict(), {"object_check": "off"})
    with pytest.raises(Exception, match="object_check_rule"):
        RefineConfig(object_check_rule="majority")


def test_the_removal_rule_counts_what_a_gaussian_alone_draws():
    """RefineConfig.object_check_rule = "removal": each Gaussian's gains are what removing it alone
    takes from the object's rendered coverage on object / background pixels (exactly, from the
    opacity gradient), so a Gaussian in front of one that already draws the object gains little
    there. Such a Gaussian, spilling past the object's edge, is kept by the IoU rule (its Σ α·T
    votes count the object pixels it merely covers first) and removed by this one; the votes
    rule's verdict is always kept; a lone straddler stays, as under the IoU rule."""
    import torch

    from cobgs.data.scene import View
    from cobgs.gaussians.model import GaussianModel
    from cobgs.refine.consistency import label_votes, object_render_check, removal_gains
    from cobgs.refine.scores import pixel_labels_from_mask
    from cobgs.render.camera import Camera
    from cobgs.render.image import render

    def gaussians(means, scales, logits):
        n = len(means)
        return GaussianModel(torch.tensor(means), torch.tensor(scales).log(),
                             torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), torch.tensor(logits),
                             torch.zeros(n, 1, 3), torch.zeros(n, 0, 3))

    def coverage(m, cam):
        with torch.no_grad():
            return render(m, cam, features=torch.ones(len(m), 1)).image[..., 0]

    # exact: on a random scene, each gain is the coverage lost by rendering without that Gaussian
    model, views, _ = tiny_scene(n_views=1, n=200)
    lab = (torch.rand(views[0].camera.height, views[0].camera.width, generator=torch.Generator().manual_seed(1)) * 3
           ).long() - 1  # −1 (ignored), 0, 1
    gains, inter, bg = removal_gains(model, views, [lab])
    full = coverage(model, views[0].camera)
    assert abs(inter - float(full[lab == 1].sum())) < 1e-3 and abs(bg - float(full[lab == 0].sum())) < 1e-3
    for i in (0, 17, 101, 199):
        keep = torch.ones(len(model), dtype=torch.bool)
        keep[i] = False
        drop = full - coverage(model.select(keep), views[0].camera)
        for k in (0, 1):
            assert abs(float(gains[i, k]) - float(drop[lab == k].sum())) < 1e-3 * max(1.0, float(drop.abs().sum()))

    cam = Camera(K=torch.tensor([[50.0, 0, 16.0], [0, 50.0, 16.0], [0, 0, 1]]), viewmat=torch.eye(4),
                 width=32, height=32, name="cam")
    # 0: an opaque Gaussian drawing the object (the mask: where it alone renders above 0.5);
    # 1: a smaller one in front of it, on the object's right edge
    model = gaussians([[0.0, 0.0, 3.0], [0.30, 0.0, 2.0]], [[0.35] * 3, [0.10] * 3], [6.0, 6.0])
    mask = coverage(model.select(torch.tensor([0])), cam) > 0.5
    view = View(camera=cam, image=torch.zeros(32, 32, 3), name="cam", masks={"obj": mask})
    px = [pixel_labels_from_mask(mask, 32, 32)]
    votes = label_votes(model, [view], px, 2)
    gains, _, _ = removal_gains(model, [view], px)
    assert votes[1, 1] > 2.5 * gains[1, 1]  # in front of the object's own Gaussian: it adds little there
    fg = torch.ones(2, dtype=torch.bool)
    assert object_render_check(model, fg, [view], px).tolist() == [True, False]
    assert object_render_check(model, fg, [view], px, rule="iou").tolist() == [True, True]
    assert object_render_check(model, fg, [view], px, rule="removal").tolist() == [True, False]
    # what the votes rule keeps stays: at λ = 0.5 it keeps the front one (14.2 > 0.5 · 27.2)
    assert object_render_check(model, fg, [view], px, mask_lambda=0.5, rule="removal").tolist() == [True, True]
    # a pole drawn by one wide Gaussian with most of its weight beside it, and one wholly beside it
    pole = gaussians([[0.0, 0.0, 2.0], [0.36, 0.0, 2.0]], [[0.15] * 3, [0.04] * 3], [4.0, 4.0])
    pm = torch.zeros(32, 32, dtype=torch.bool)
    pm[:, 14:18] = True
    pv = View(camera=cam, image=torch.zeros(32, 32, 3), name="cam", masks={"pole": pm})
    ppx = [pixel_labels_from_mask(pm, 32, 32)]
    assert object_render_check(pole, fg, [pv], ppx, rule="removal").tolist() == [True, False]
    assert RefineConfig(object_check_rule="removal").object_check_rule == "removal"


def test_refine_applies_the_object_check_only_when_asked():
    """The default object_check ("per_use") may only shrink the released foreground for the
    object alone and keeps the released one for the scene; "off" is the authors'
    segmentation; the no-split row forces it off."""
    import dataclasses

    from cobgs.refine.peers import nosplit_config

    model, views, extent = tiny_scene(n_views=3)
    masks = masks_for(views, "ball")
    # the labels' verdict alone in the scene (the undecided ones the votes add: the next test)
    cfg = RefineConfig(stage_length_views=1.0, mask_stages=2, in_scene_undecided="labels")
    on = refine(model, views, masks, extent, cfg, progress=False)
    off = refine(model, views, masks, extent, dataclasses.replace(cfg, object_check="off"), progress=False)
    assert torch.equal(on.model.data["mask_logit"], off.model.data["mask_logit"])  # same refinement
    assert not (on.foreground & ~off.foreground).any()
    assert on.config["object_check_dropped"] == int((off.foreground & ~on.foreground).sum())
    assert off.config["object_check_dropped"] == 0
    assert nosplit_config(cfg).object_check == "off"
    assert RefineConfig().object_check == "per_use"
    assert torch.equal(on.foreground_in_scene, off.foreground) and off.foreground_in_scene is None


def test_per_use_gives_the_checked_set_alone_and_the_labels_verdict_in_the_scene(monkeypatch):
    """object_check = "per_use": one refinement, two outputs: the checked foreground for the
    object alone, the labels' verdict (the released segmentation) for the object within the
    scene. (The check is replaced by one that drops the whole foreground, so that the two sets
    differ on this small scene.)"""
    import cobgs.refine.alternation as A

    model, views, extent = tiny_scene(n_views=3)
    masks = masks_for(views, "ball")
    cfg = RefineConfig(stage_length_views=8.0, mask_stages=1,  # 24 iterations: labels pass 0.9
                       in_scene_undecided="labels")
    monkeypatch.setattr(A, "object_render_check", lambda m, fg, *a, **k: torch.zeros_like(fg))
    off = refine(model, views, masks, extent, dataclasses.replace(cfg, object_check="off"), progress=False)
    vis = refine(model, views, masks, extent, dataclasses.replace(cfg, object_check="visible"), progress=False)
    use = refine(model, views, masks, extent, dataclasses.replace(cfg, object_check="per_use"), progress=False)
    assert off.foreground.any() and not vis.foreground.any()
    assert torch.equal(use.model.data["mask_logit"], off.model.data["mask_logit"])
    assert torch.equal(use.foreground, vis.foreground)
    assert torch.equal(use.foreground_in_scene, off.foreground)
    assert vis.foreground_in_scene is None
    assert use.config["object_check_dropped"] == vis.config["object_check_dropped"] > 0


def test_the_undecided_gaussians_the_votes_call_object_join_the_object_in_the_scene():
    """RefineConfig.in_scene_undecided = "votes" (issue 59 item 2): the object within the scene
    is the labels' verdict plus every undecided Gaussian (0.1 < label < 0.9) whose Σ α·T votes
    of the training masks say object; the refinement itself and the object-alone output do not
    change. On the check scene: an undecided Gaussian in the object joins, undecided ones on
    background pixels and decided ones do not."""
    from cobgs.configs import key_without_later
    from cobgs.refine.consistency import label_votes, undecided_by_votes

    scene_model, scene_view = _check_scene()
    spx = [pixel_labels_from_mask(scene_view.masks["obj"], 32, 32)]
    values = torch.full((len(scene_model),), 0.5)
    values[1:41] = 0.95  # decided (label > 0.9): never added, whatever its votes
    votes = label_votes(scene_model, [scene_view], spx, 2)
    joined = undecided_by_votes(values, votes)
    assert joined[0] and not joined[1:].any()  # A, in the object; the patch and the wall lie on background
    assert not undecided_by_votes(torch.full_like(values, 0.95), votes).any()

    model, views, extent = tiny_scene(n_views=3)
    masks = masks_for(views, "ball")
    # stages of 3 iterations: split children cannot pass 0.9, so many Gaussians end undecided
    cfg = RefineConfig(stage_length_views=1.0, mask_stages=2)
    labels = refine(model, views, masks, extent, dataclasses.replace(cfg, in_scene_undecided="labels"), progress=False)
    votes = refine(model, views, masks, extent, cfg, progress=False)  # the default since 2026-11-29
    assert torch.equal(labels.model.data["mask_logit"], votes.model.data["mask_logit"])  # the same refinement
    assert torch.equal(labels.foreground, votes.foreground)  # the same object alone
    added = votes.foreground_in_scene & ~labels.foreground_in_scene
    assert not (labels.foreground_in_scene & ~votes.foreground_in_scene).any() and added.any()
    v = votes.mask_values
    assert ((v[added] > 0.1) & (v[added] < 0.9)).all()
    px = [pixel_labels_from_mask(masks[i], w.camera.height, w.camera.width) for i, w in enumerate(views)]
    w = label_votes(votes.model, views, px, 2)
    assert (w[added, 1] > w[added, 0]).all()
    # in the key only where it changes something: the check per use, the new value
    assert RefineConfig().in_scene_undecided == "votes"
    assert "in_scene_undecided" not in key_without_later(RefineConfig, RefineConfig(in_scene_undecided="labels").as_dict())
    assert key_without_later(RefineConfig, RefineConfig().as_dict())["in_scene_undecided"] == "votes"
    for check in ("off", "visible"):
        d = RefineConfig(object_check=check, in_scene_undecided="votes").as_dict()
        assert "in_scene_undecided" not in key_without_later(RefineConfig, d)
    with pytest.raises(Exception, match="in_scene_undecided"):
        RefineConfig(in_scene_undecided="all")


def test_short_stages_cannot_carry_a_restarted_label_past_foreground_and_say_so(caplog):
    """Adam at lr 0.1 with a gradient of one sign moves a logit by lr per step: 21 steps
    leave a label from 0.5 below 0.9, 22 pass it. A splitting schedule with shorter stages
    (9 views x 2 = 18 iterations, the LERF-mask fixture) is named in a warning."""
    import logging

    from cobgs.refine.alternation import short_stage_warning

    need = RefineConfig(label_lr=0.1).steps_to_foreground()
    assert need == 22 and RefineConfig(label_lr=0.05).steps_to_foreground() == 44
    for steps, passes in ((need - 1, False), (need, True)):
        logit = torch.zeros(1, requires_grad=True)
        opt = torch.optim.Adam([logit], lr=0.1, eps=1e-15)
        for _ in range(steps):
            opt.zero_grad()
            (-logit).sum().backward()  # the object's pixels pull the label up
            opt.step()
        assert (torch.sigmoid(logit).item() > 0.9) is passes, steps
    cfg = RefineConfig()
    msg = short_stage_warning(cfg, 9)
    assert msg and "18 iterations" in msg and "stage_length_views >= 2.5" in msg
    assert short_stage_warning(cfg, 11) is None  # 22 iterations
    assert short_stage_warning(dataclasses.replace(cfg, stage_length_views=2.5), 9) is None
    assert short_stage_warning(dataclasses.replace(cfg, bags=False), 3) is None  # nothing restarts

    model, views, extent = tiny_scene(n_views=3)
    with caplog.at_level(logging.WARNING, logger="cobgs.refine.alternation"):
        refine(model, views, masks_for(views, "ball"), extent, RefineConfig(mask_stages=2, stage_length_views=2),
               progress=False, object_name="ball")
    assert any("stages of 6 iterations" in r.getMessage() and "ball" in r.getMessage() for r in caplog.records)


def test_object_share_is_the_minority_part_over_the_objects_whole():
    """Issue 59 item 2 (RefineConfig.split_object_share): per Gaussian, min(object, background)
    Σ α·T over the object's Σ α·T of the view; 0 everywhere where the view shows no object."""
    from cobgs.refine.scores import object_share

    w = torch.tensor([[9.0, 1.0], [0.0, 4.0], [5.0, 5.0], [100.0, 2.0]])
    s = object_share(w)
    assert torch.allclose(s, torch.tensor([1.0, 0.0, 5.0, 2.0]) / 12.0)
    assert not object_share(torch.tensor([[3.0, 0.0], [1.0, 0.0]])).any()
    with pytest.raises(InputError, match=r"\[N, 2\]"):
        object_share(torch.ones(4, 3))


def test_split_object_share_splits_what_eq6_calls_unambiguous_and_never_prunes_it():
    """A Gaussian whose stage-mean object share reaches the bar joins the split set although its
    Eq. 6 score is above δ; it is split when large, left alone by RAEM; at 0 (COB-GS as
    published) nothing is accumulated and the field stays out of the cache key, so entries
    written before it existed are reused."""
    from cobgs.configs import key_without_later

    model, views, extent = tiny_scene(n_views=3)
    off = Refiner(model.clone(), views, masks_for(views, "ball"), extent,
                  RefineConfig(stage_length_views=2, split_object_share=0.0))
    assert off.object_share is None
    assert RefineConfig().split_object_share == 0.05  # the default since issue 59
    assert "split_object_share" not in key_without_later(RefineConfig, RefineConfig(split_object_share=0.0).as_dict())
    assert key_without_later(RefineConfig, RefineConfig().as_dict())["split_object_share"] == 0.05

    cfg = RefineConfig(stage_length_views=2, split_size_fraction=0.0, split_object_share=1e-3)
    L = cfg.stage_length(3)
    for last in (False, True):
        m = model.clone()
        r = Refiner(m, views, masks_for(views, "ball"), extent, cfg)
        for _ in range(L):
            r.mask_step(r.next_view())
        amb = r.scores.ambiguous(cfg.threshold, L)
        wide = (r.object_share.mean(L) >= cfg.split_object_share) & ~amb
        assert wide.any()  # the bar is low: some Gaussians Eq. 6 calls clear are wide for the object
        n0 = len(m)
        info = r.end_mask_stage(L, last=last)
        assert info["object_share"] == int(wide.sum())
        if last:  # RAEM judges by Eq. 6 alone
            assert info["split"] == 0 and info["pruned"] <= int(amb.sum())
            if r.raem_keep is not None:
                assert r.raem_keep[wide].all()
        else:
            assert info["split"] == int((amb | wide).sum()) and len(m) == n0 + info["split"]
        assert r.object_share.iterations == 0 and r.object_share.sum.shape == (len(m),)
