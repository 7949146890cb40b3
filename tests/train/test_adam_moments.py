"""The baseline's Adam moments: export, file round trip, errors, and the COB-GS texture
stages continuing them (the released code restores its 3DGS checkpoint's optimizer)."""

from __future__ import annotations

import logging

import pytest
import torch

from cobgs.train.adam_moments import MOMENTS_FILE, export_moments, load_moments, read_moments, save_moments
from cobgs.errors import DataError, InputError
from cobgs.train.losses import photometric_loss
from cobgs.refine.alternation import Refiner, masks_for, refine, refine_objects
from cobgs.configs import RefineConfig
from cobgs.render.image import render
from refine_fixtures import tiny_scene

TEXTURE = ("means", "sh0", "shN", "opacity_logits", "log_scales", "quats")


def _texture_lrs(cfg: RefineConfig, extent: float) -> dict:
    return {"means": cfg.position_lr * extent, "sh0": cfg.sh0_lr, "shN": cfg.shN_lr,
            "opacity_logits": cfg.opacity_lr, "log_scales": cfg.scaling_lr, "quats": cfg.rotation_lr}


def _photometric_steps(model, views, opt, steps: int, start: int = 0) -> None:
    for k in range(start, start + steps):
        v = views[k % len(views)]
        out = render(model, v.camera, torch.zeros(3))
        photometric_loss(out.image, v.image).backward()
        opt.step()
        opt.zero_grad(set_to_none=True)


@pytest.fixture
def baseline():
    """A tiny scene whose texture parameters an Adam ("the baseline") has stepped a while,
    from perturbed colours and opacities so that the gradients are not zero."""
    model, views, extent = tiny_scene(n_views=4)
    with torch.no_grad():
        g = torch.Generator().manual_seed(1)
        model.data["sh0"].add_(0.4 * torch.randn(model.sh0.shape, generator=g))
        model.data["opacity_logits"].add_(0.5 * torch.randn(model.opacity_logits.shape, generator=g))
    cfg = RefineConfig()
    opt = model.make_adam(_texture_lrs(cfg, extent))
    _photometric_steps(model, views, opt, 24)
    return model, views, extent, opt


def test_export_then_load_continues_adam_bitwise(baseline):
    model, views, extent, opt = baseline
    mom = export_moments(opt)
    assert sorted(mom) == sorted(TEXTURE)
    assert all(float(mom[k]["step"]) == 24 for k in TEXTURE)
    twin = model.clone()
    opt2 = twin.make_adam(_texture_lrs(RefineConfig(), extent))
    assert sorted(load_moments(opt2, mom)) == sorted(TEXTURE)
    # Copies, not the same tensors (the fused step updates them in place).
    assert opt2.state[twin.means]["exp_avg"].data_ptr() != mom["means"]["exp_avg"].data_ptr()
    _photometric_steps(model, views, opt, 3, start=24)
    _photometric_steps(twin, views, opt2, 3, start=24)
    for k in TEXTURE:
        assert torch.equal(model.data[k], twin.data[k]), k


def test_moments_file_round_trip_and_errors(baseline, tmp_path):
    model, _, _, opt = baseline
    mom = export_moments(opt)
    path = save_moments(tmp_path / MOMENTS_FILE, mom, len(model))
    assert [p.name for p in tmp_path.iterdir()] == [MOMENTS_FILE]  # no temporary left behind
    back = read_moments(path, len(model))
    for k in TEXTURE:
        for key in ("exp_avg", "exp_avg_sq", "step"):
            assert torch.equal(back[k][key], mom[k][key]), (k, key)
    with pytest.raises(DataError, match="num_gaussians.*599"):
        read_moments(path, len(model) - 1)
    with pytest.raises(DataError, match="not found"):
        read_moments(tmp_path / "missing.pt")
    torch.save({"format": "something-else"}, tmp_path / "other.pt")
    with pytest.raises(DataError, match="other.pt.*not a cobgs-adam-moments file"):
        read_moments(tmp_path / "other.pt")
    raw = path.read_bytes()
    (tmp_path / "cut.pt").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(DataError, match="cut.pt: unreadable"):
        read_moments(tmp_path / "cut.pt")
    bad = {k: dict(v) for k, v in mom.items()}
    bad["quats"] = {"exp_avg": mom["quats"]["exp_avg"], "step": mom["quats"]["step"]}
    torch.save({"format": "cobgs-adam-moments", "version": 1, "num_gaussians": len(model), "tensors": bad},
               tmp_path / "nokey.pt")
    with pytest.raises(DataError, match="quats"):
        read_moments(tmp_path / "nokey.pt")
    with pytest.raises(InputError, match="rows"):
        save_moments(tmp_path / "x.pt", mom, len(model) + 1)


def test_load_moments_names_the_mismatch(baseline):
    model, _, extent, opt = baseline
    mom = export_moments(opt)
    other = model.clone()
    other.keep(torch.arange(len(other)) < 500)
    with pytest.raises(InputError, match=r"means.exp_avg has shape \[600, 3\].*\[500, 3\]"):
        load_moments(other.make_adam({"means": 1e-3}), mom, "adam_moments.pt")


def test_a_tensor_training_never_stepped_starts_from_zero_moments(baseline):
    """Issue 44 M6: below the first SH-degree step (1000 iterations) training never steps
    ``shN``, so its moments are not exported, and loading them failed every COB-GS refinement
    (`cobgs run workflows/demo.toml --set train.iterations=60`). A missing moment is a zero
    moment: the tensor's next step is Adam's first, the others continue."""
    model, views, extent, opt = baseline
    mom = {k: v for k, v in export_moments(opt).items() if k != "shN"}
    twin = model.clone()
    opt2 = twin.make_adam(_texture_lrs(RefineConfig(), extent))
    assert sorted(load_moments(opt2, mom)) == sorted(k for k in TEXTURE if k != "shN")
    assert not opt2.state.get(twin.data["shN"])
    fresh = model.clone()
    opt3 = fresh.make_adam(_texture_lrs(RefineConfig(), extent))
    _photometric_steps(twin, views, opt2, 1)
    _photometric_steps(fresh, views, opt3, 1)
    assert torch.equal(twin.data["shN"], fresh.data["shN"])  # shN: exactly a fresh Adam's step
    assert float(opt2.state[twin.data["means"]]["step"]) == 25  # the rest continues
    r = refine(model.clone(), views, masks_for(views, "ball"), extent,
               RefineConfig(mask_stages=1, stage_length_views=1), texture_moments=mom, progress=False)
    assert r.config["texture_adam"] == "baseline"


def test_texture_stage_continues_the_baseline_optimizer(baseline):
    """With the baseline's moments the first TEXTURE step is exactly the step the baseline's
    own Adam would take next (same lrs, same view); with fresh moments it is a
    sign-like step of about one learning rate for every parameter with a gradient."""
    model, views, extent, opt = baseline
    mom = export_moments(opt)
    masks = masks_for(views, "ball")
    warm = Refiner(model.clone(), views, masks, extent, RefineConfig(), texture_moments=mom)
    fresh = Refiner(model.clone(), views, masks, extent, RefineConfig())
    ignored = Refiner(model.clone(), views, masks, extent, RefineConfig(texture_adam="fresh"), texture_moments=mom)
    assert (warm.texture_adam, fresh.texture_adam, ignored.texture_adam) == ("baseline", "fresh", "fresh")
    assert not ignored.texture_opt.state
    before = model.opacity_logits.detach().clone()
    warm.texture_step(0)
    fresh.texture_step(0)
    _photometric_steps(model, views, opt, 1, start=0)  # the baseline continues on view 0
    for k in TEXTURE:
        assert torch.equal(warm.model.data[k], model.data[k]), k
    d_warm = (warm.model.opacity_logits.detach() - before).abs()
    d_fresh = (fresh.model.opacity_logits.detach() - before).abs()
    moved = d_fresh > 0
    assert moved.sum() > 100
    assert torch.allclose(d_fresh[moved], torch.full_like(d_fresh[moved], RefineConfig().opacity_lr), rtol=1e-3)
    assert d_warm[moved].mean() < 0.5 * d_fresh[moved].mean()


def test_refine_records_how_the_texture_adam_started(baseline, caplog):
    model, views, extent, opt = baseline
    mom = export_moments(opt)
    cfg = RefineConfig(mask_stages=2, stage_length_views=1)
    with caplog.at_level(logging.WARNING, logger="cobgs.refine.alternation"):
        cold = refine(model, views, masks_for(views, "ball"), extent, cfg, progress=False, object_name="ball")
    assert cold.config["texture_adam"] == "fresh" and cold.texture_moments is None
    assert any("no baseline Adam moments" in r.getMessage() for r in caplog.records)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="cobgs.refine.alternation"):
        warm = refine(model, views, masks_for(views, "ball"), extent, cfg, progress=False, texture_moments=mom,
                      return_moments=True)
    assert warm.config["texture_adam"] == "baseline"
    assert not any("Adam" in r.getMessage() for r in caplog.records)  # (this tiny schedule's short-stage warning may remain)
    # The returned moments follow the refined model (splits appended children).
    assert warm.texture_moments["means"]["exp_avg"].shape == warm.model.means.shape
    assert float(warm.texture_moments["means"]["step"]) == 24 + len(views)  # one texture stage of V its
    # The input moments were copied, not stepped in place.
    assert float(mom["means"]["step"]) == 24


def test_refine_objects_chains_the_texture_moments(baseline, monkeypatch):
    import cobgs.refine.alternation as refine_mod

    model, views, extent, opt = baseline
    mom = export_moments(opt)
    seen = []
    real = refine_mod.load_moments

    def spy(optimizer, moments, source="moments"):
        seen.append(float(moments["means"]["step"]))
        return real(optimizer, moments, source)

    monkeypatch.setattr(refine_mod, "load_moments", spy)
    masks = {"ball": masks_for(views, "ball"), "cube": masks_for(views, "cube")}
    mo = refine_objects(model, views, masks, extent, RefineConfig(mask_stages=2, stage_length_views=1),
                        progress=False, texture_moments=mom)
    # The second object continues where the first object's texture stage left the Adam.
    assert seen == [24.0, 24.0 + len(views)]
    assert [r["config"]["texture_adam"] for r in mo.refinements] == ["baseline", "baseline"]


def test_the_same_moments_are_the_same_bytes(tmp_path):
    """Two saves of the same moments give identical files (torch.save names its records
    after the file, and the temporary name is random): a recomputed train entry with the
    same content has the same hash, so nothing downstream re-runs."""
    import subprocess
    import sys

    code = ("import sys, torch\nfrom cobgs.train.adam_moments import save_moments\n"
            "g = torch.Generator().manual_seed(0)\n"
            "m = {'means': {'exp_avg': torch.randn(7, 3, generator=g), 'exp_avg_sq': torch.rand(7, 3, generator=g),"
            " 'step': torch.tensor(5.0)}}\n"
            "save_moments(sys.argv[1], m, 7)\n")
    for name in ("a", "b"):  # separate processes, as two runs are
        subprocess.run([sys.executable, "-c", code, str(tmp_path / name / "adam_moments.pt")], check=True)
    assert (tmp_path / "a" / "adam_moments.pt").read_bytes() == (tmp_path / "b" / "adam_moments.pt").read_bytes()
