"""NG-GS's boundary stage (cobgs.refine.ngs) against the rules of its released code
(BJTU-KD3D/NG-GS scene/ngs_model.py, train.py; docs/method.md §3 "NG-GS")."""

from __future__ import annotations

import math

import pytest
import torch

from cobgs.configs import NGSConfig, RefineConfig
from cobgs.refine.alternation import Refiner, masks_for, refine
from cobgs.refine.methods import NGSRun, REGISTRY, run_method
from cobgs.refine.ngs import (PRIMES, BoundaryRefiner, HashEncoding, NGSStage, boundary_indices, boundary_scores,
                              rbf_interpolate)
from refine_fixtures import tiny_scene


def test_boundary_selection_is_the_label_ambiguity_plus_the_weak_signal_top_k():
    logits = torch.tensor([0.0, 4.0, -4.0, 0.5, 10.0])
    p = torch.sigmoid(logits)
    torch.testing.assert_close(boundary_scores(logits), 4 * p * (1 - p))
    accum = torch.tensor([0.0, 2.0, 4.0, 1.0, 4.0])  # the mask-signal accumulator (high: clear)
    torch.testing.assert_close(boundary_scores(logits, accum), 4 * p * (1 - p) + 1 - accum / 4)
    assert torch.equal(boundary_scores(logits, torch.zeros(5)), boundary_scores(logits))  # empty: label term only
    s = boundary_scores(logits)
    assert boundary_indices(s, 2).tolist() == [0, 3]  # the two most ambiguous
    assert sorted(boundary_indices(s, 99).tolist()) == [0, 1, 2, 3, 4]
    g = torch.Generator().manual_seed(0)
    idx = boundary_indices(torch.zeros(6), 3, g)  # no score: a random subset
    assert len(idx) == 3 and len(set(idx.tolist())) == 3


def test_hash_encoding_levels_hash_and_box():
    enc = HashEncoding(levels=8, features_per_level=2, log2_hashmap_size=15, base_resolution=16, finest_resolution=512)
    scale = math.exp((math.log(512) - math.log(16)) / 7)
    assert [enc.resolution(k) for k in range(8)] == [int(16 * scale ** k) for k in range(8)]
    assert enc.resolution(0) == 16 and enc.resolution(7) in (511, 512) and enc.out_dim == 16
    c = torch.tensor([[3, 5, 7], [0, 0, 0], [1, 0, 0]])
    want = [((3 * PRIMES[0]) ^ (5 * PRIMES[1]) ^ (7 * PRIMES[2])) % 2 ** 15, 0, PRIMES[0] % 2 ** 15]
    assert enc.hash(c).tolist() == want
    xyz = torch.tensor([[1.0, 2.0, 3.0], [3.0, 2.5, 4.0], [2.0, 3.0, 5.0]])
    unit = HashEncoding.normalize(xyz)
    torch.testing.assert_close(unit, torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.5, 0.5], [0.5, 1.0, 1.0]]))
    # the features of a point are the table rows of its floored cell at each level
    f = enc(xyz)
    k0 = enc.hash(torch.floor(unit * 16).long())
    torch.testing.assert_close(f[:, :2], enc.tables[0][k0])


def test_rbf_interpolation_and_continuity_by_hand():
    xyz = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    v = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.5, 0.5, 0.5]])
    interp, cont = rbf_interpolate(xyz, v, k_neighbors=2)
    # neighbours by distance (the point itself dropped): 0 -> (1 at 1, 2 at 3); 1 -> (0 at 1, 2 at 2);
    # 2 -> (1 at 2, 0 at 3); sigma = mean(1, 3, 1, 2, 2, 3) = 2
    d = torch.tensor([[1.0, 3.0], [1.0, 2.0], [2.0, 3.0]])
    nb = [[1, 2], [0, 2], [1, 0]]
    w = torch.exp(-d ** 2 / (2 * 2.0 ** 2))
    w = w / w.sum(1, keepdim=True)
    want = torch.stack([(w[i, :, None] * v[nb[i]]).sum(0) for i in range(3)])
    torch.testing.assert_close(interp, want)
    # summed over channels, averaged over every (point, neighbour) pair: the released .sum(-1).mean()
    want_cont = torch.stack([w[i] * ((v[i] - v[nb[i]]) ** 2).sum(-1) for i in range(3)]).mean()
    torch.testing.assert_close(cont, want_cont)


def test_the_refiner_predicts_a_bounded_correction_of_the_base_colour():
    ref = BoundaryRefiner(NGSConfig(seed=3))
    xyz, base = torch.rand(50, 3), torch.rand(50, 3)
    rgb, density = ref(xyz, base)
    assert rgb.shape == (50, 3) and density.shape == (50, 1) and bool((density >= 0).all())
    assert float((rgb - base).detach().abs().max()) <= 0.1 + 1e-6  # base + 0.1 tanh(.), clamped to [0, 1]
    again = BoundaryRefiner(NGSConfig(seed=3))
    assert all(torch.equal(a, b) for a, b in zip(ref.parameters(), again.parameters()))  # seeded


@pytest.fixture(scope="module")
def scene():
    model, views, extent = tiny_scene(n_views=4)
    return model, views, extent


def test_the_loss_acts_in_texture_stages_only(scene, monkeypatch):
    model, views, extent = scene
    calls = []
    real = NGSStage.loss

    def spy(self, *a, **k):
        calls.append(r.iteration)
        return real(self, *a, **k)

    monkeypatch.setattr(NGSStage, "loss", spy)
    cfg = RefineConfig(mask_stages=2, stage_length_views=1)
    r = Refiner(model.clone(), views, masks_for(views, "ball"), extent, cfg, ngs=NGSConfig(max_points=64))
    r.run(progress=False)
    plan, length = cfg.plan(), cfg.stage_length(len(views))
    texture_its = [si * length + k for si, kind in enumerate(plan) if kind == "texture" for k in range(length)]
    assert calls == texture_its and calls  # every texture iteration, no mask iteration
    before = {k: p.detach().clone() for k, p in r.ngs.refiner.named_parameters()}
    r.texture_step(0)
    assert any(not torch.equal(before[k], p) for k, p in r.ngs.refiner.named_parameters())  # its Adam stepped


def test_the_boundary_gaussians_receive_gradients_through_position_and_dc_colour(scene):
    model, views, extent = scene
    m = model.clone()
    from cobgs.refine.scores import ensure_label

    ensure_label(m, "mask_logit", reset=True)
    stage = NGSStage(NGSConfig(max_points=32), m.device)
    loss = stage.loss(m, "mask_logit")
    loss.backward()
    for name in ("means", "sh0"):
        g = m.data[name].grad
        assert g is not None and int((g.reshape(len(m), -1).abs().sum(1) > 0).sum()) <= 32 and float(g.abs().sum()) > 0
    assert m.data["opacity_logits"].grad is None or float(m.data["opacity_logits"].grad.abs().sum()) == 0


def test_without_the_stage_the_refinement_is_cobgs_bit_for_bit(scene):
    model, views, extent = scene
    cfg = RefineConfig(mask_stages=2, stage_length_views=1, object_check="off")
    a = refine(model, views, masks_for(views, "ball"), extent, cfg, progress=False)
    b = run_method("cobgs", model, views, masks_for(views, "ball"), extent, config=cfg, progress=False)
    for k in a.model.data:
        assert torch.equal(a.model.data[k], b.model.data[k]), k
    assert torch.equal(a.foreground, b.foreground)
    n = run_method("ngs", model, views, masks_for(views, "ball"), extent,
                   config=NGSRun(cfg, NGSConfig(max_points=64)), progress=False)
    assert n.method == "ngs" and n.config["ngs"]["max_points"] == 64
    assert not torch.equal(n.model.data["sh0"], a.model.data["sh0"])  # the stage changed the texture stages
    assert REGISTRY["ngs"].label == "NG-GS" and REGISTRY["ngs"].sections == ("cobgs", "ngs")
