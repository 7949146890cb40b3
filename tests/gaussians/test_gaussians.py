"""Gaussian model: initialisation, extras, and optimizer-consistent structural edits."""

import math

import pytest
import torch

from cobgs.errors import InputError
from cobgs.gaussians.model import GaussianModel, knn_mean_sq_dist, quat_to_rotmat


def _model(n=20, seed=0):
    g = torch.Generator().manual_seed(seed)
    m = GaussianModel(
        torch.randn(n, 3, generator=g),
        torch.randn(n, 3, generator=g) * 0.3 - 2,
        torch.randn(n, 4, generator=g),
        torch.randn(n, generator=g),
        torch.randn(n, 1, 3, generator=g),
        torch.randn(n, 15, 3, generator=g),
    )
    m.add_extra("label_logits", torch.randn(n, generator=g), fill=0.0)
    m.add_extra("object_id", torch.arange(n) + 100, fill=-1)
    return m


def _two_optimizers(m):
    """A texture optimizer and a label optimizer, as in COB-GS, after one real step each."""
    tex = m.make_adam({"means": 1e-3, "log_scales": 1e-2, "quats": 1e-3, "opacity_logits": 0.05, "sh0": 1e-2, "shN": 1e-3})
    lab = m.make_adam({"label_logits": 0.1})
    loss = sum((t.float() ** 2).sum() * (i + 1) for i, t in enumerate(m.parameters(["means", "log_scales", "quats", "opacity_logits", "sh0", "shN", "label_logits"])))
    loss.backward()
    tex.step()
    lab.step()
    tex.zero_grad()
    lab.zero_grad()
    return tex, lab


def _state(opt, p):
    return opt.state[p]


def test_from_points_nearest_neighbour_scales():
    # Points on a line with spacing 1 (ends) / known neighbours.
    xyz = torch.tensor([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0], [10, 0, 0]])
    m = GaussianModel.from_points(xyz, torch.rand(5, 3))
    # point 0: neighbours at 1, 2, 3 → mean sq = (1 + 4 + 9) / 3
    assert m.scales[0, 0].item() == pytest.approx(math.sqrt(14 / 3), rel=1e-5)
    # point 1: neighbours at distances 1, 1, 2 → (1 + 1 + 4) / 3
    assert m.scales[1, 0].item() == pytest.approx(math.sqrt(2.0), rel=1e-5)
    assert torch.allclose(m.scales[:, 0], m.scales[:, 2])
    assert torch.allclose(m.opacities, torch.full((5,), 0.1))
    assert torch.equal(m.quats, torch.tensor([[1.0, 0, 0, 0]]).repeat(5, 1))
    assert m.sh_degree == 3 and m.active_sh_degree == 0 and m.shN.shape == (5, 15, 3)
    # Duplicate points get the floor instead of log(0).
    d = knn_mean_sq_dist(torch.zeros(4, 3))
    assert torch.all(d == 0)
    assert torch.isfinite(GaussianModel.from_points(torch.zeros(4, 3)).log_scales).all()


def test_random_in_box():
    g = torch.Generator().manual_seed(0)
    m = GaussianModel.random_in_box(2000, [-1, 0, 2], [1, 1, 3], generator=g, sh_degree=1)
    lo, hi = m.means.min(0).values, m.means.max(0).values
    assert torch.all(lo >= torch.tensor([-1.0, 0, 2])) and torch.all(hi <= torch.tensor([1.0, 1, 3]))
    assert (hi - lo).min() > 0.9
    assert m.shN.shape == (2000, 3, 3)
    m2 = GaussianModel.random_in_box(2000, [-1, 0, 2], [1, 1, 3], generator=torch.Generator().manual_seed(0), sh_degree=1)
    assert torch.equal(m.means, m2.means)  # deterministic for a seed


def test_keep_prunes_tensors_and_both_optimizers():
    m = _model()
    tex, lab = _two_optimizers(m)
    before = {k: v.detach().clone() for k, v in m.data.items()}
    st_means = {k: v.clone() for k, v in _state(tex, m.means).items()}
    st_lab = {k: v.clone() for k, v in _state(lab, m.label_logits).items()}
    keep = torch.zeros(20, dtype=torch.bool)
    keep[[1, 4, 5, 19]] = True
    m.keep(keep, [tex, lab])
    assert len(m) == 4
    for k, v in m.data.items():
        assert torch.equal(v.detach(), before[k][keep]), k
    # Optimizers point at the new tensors and carry the matching rows of their moments.
    assert tex.param_groups[0]["params"][0] is m.means
    assert lab.param_groups[0]["params"][0] is m.label_logits
    s = _state(tex, m.means)
    assert torch.equal(s["exp_avg"], st_means["exp_avg"][keep])
    assert torch.equal(s["exp_avg_sq"], st_means["exp_avg_sq"][keep])
    assert torch.equal(s["step"], st_means["step"])
    assert torch.equal(_state(lab, m.label_logits)["exp_avg"], st_lab["exp_avg"][keep])
    assert len(tex.state) == 6 and len(lab.state) == 1  # no stale entries for old tensors


def test_replace_with_split_children_keeps_state_in_sync():
    m = _model()
    tex, lab = _two_optimizers(m)
    st_old = _state(tex, m.opacity_logits)["exp_avg"].clone()
    parents = torch.zeros(20, dtype=torch.bool)
    parents[[2, 7]] = True
    children = m.split_children(parents, 2, 1.6, reset=["label_logits"], generator=torch.Generator().manual_seed(0))
    assert children["means"].shape == (4, 3)
    assert torch.allclose(children["log_scales"], m.log_scales.detach()[[2, 7, 2, 7]] - math.log(1.6))
    assert torch.equal(children["label_logits"], torch.zeros(4))  # reset to the fill value
    assert torch.equal(children["object_id"], torch.tensor([102, 107, 102, 107]))  # inherited
    assert torch.equal(children["sh0"], m.sh0.detach()[[2, 7, 2, 7]])
    m.replace(parents, children, [tex, lab])
    assert len(m) == 22
    for opt in (tex, lab):
        for group in opt.param_groups:
            p = group["params"][0]
            assert p is m.data[group["name"]]
            st = opt.state[p]
            assert st["exp_avg"].shape == p.shape and st["exp_avg_sq"].shape == p.shape
            assert torch.all(st["exp_avg"][-4:] == 0) and torch.all(st["exp_avg_sq"][-4:] == 0)
    assert torch.equal(_state(tex, m.opacity_logits)["exp_avg"][:18], st_old[~parents])
    # Training continues without shape errors on both optimizers.
    (m.means.sum() + m.label_logits.sum()).backward()
    tex.step()
    lab.step()


def test_split_samples_follow_parent_gaussian():
    m = GaussianModel(
        torch.tensor([[1.0, -2.0, 0.5]]),
        torch.log(torch.tensor([[0.5, 0.1, 0.2]])),
        torch.tensor([[0.9, 0.2, -0.3, 0.1]]),
        torch.zeros(1),
        torch.zeros(1, 1, 3),
        torch.zeros(1, 0, 3),
    )
    ch = m.split_children(torch.tensor([0]), 40_000, generator=torch.Generator().manual_seed(3))
    x = ch["means"].double()
    R = quat_to_rotmat(m.quats.detach())[0].double()
    cov_ref = R @ torch.diag(torch.tensor([0.5, 0.1, 0.2], dtype=torch.float64) ** 2) @ R.T
    assert torch.allclose(x.mean(0), torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64), atol=0.01)
    assert torch.allclose(torch.cov(x.T), cov_ref, atol=0.005)


def test_append_fills_missing_extras_and_checks_shapes():
    m = _model(5)
    new = {k: v.detach()[:2].clone() for k, v in m.data.items() if k not in ("label_logits", "object_id")}
    m.append(new)
    assert len(m) == 7
    assert torch.equal(m.object_id[-2:], torch.tensor([-1, -1]))
    assert torch.equal(m.label_logits.detach()[-2:], torch.zeros(2))
    bad = dict(new)
    bad["means"] = torch.zeros(2, 4)
    with pytest.raises(InputError, match="means"):
        m.append(bad)
    with pytest.raises(InputError, match="core"):
        m.append({"means": torch.zeros(1, 3)})
    with pytest.raises(InputError, match="mask"):
        m.keep(torch.ones(3, dtype=torch.bool))


def test_select_is_independent_and_extras_validated():
    m = _model(6)
    sub = m.select(torch.tensor([True, False, True, False, False, True]))
    assert len(sub) == 3 and sub.extras == ["label_logits", "object_id"]
    sub.means.data.zero_()
    assert not torch.all(m.means == 0)
    for bad in ("label_0", "x", "scale_x", "f_dc_extra", "2bad"):
        with pytest.raises(InputError):
            m.add_extra(bad, 0.0)
    with pytest.raises(InputError, match="already"):
        m.add_extra("label_logits", 0.0)


def test_set_tensor_resets_moments():
    m = _model(5)
    tex, _ = _two_optimizers(m)
    assert torch.any(_state(tex, m.opacity_logits)["exp_avg"] != 0)
    m.set_tensor("opacity_logits", torch.full((5,), -4.0), [tex])
    assert torch.all(_state(tex, m.opacity_logits)["exp_avg"] == 0)
    assert tex.param_groups[3]["params"][0] is m.opacity_logits


def test_state_dict_round_trip():
    m = _model(4)
    m.active_sh_degree = 2
    r = GaussianModel.from_state_dict(m.state_dict())
    assert r.active_sh_degree == 2 and r.fill == m.fill
    for k in m.data:
        assert torch.equal(r.data[k], m.data[k])
