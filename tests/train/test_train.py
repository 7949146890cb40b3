"""Baseline training: schedules, densification bookkeeping, determinism, resume, learning."""

import math

import pytest
import torch

from cobgs.render.camera import Camera
from cobgs.data.scene import View, make_scene
from cobgs.errors import DataError, InputError
from cobgs.gaussians.model import GaussianModel
from cobgs.render.image import render
from cobgs.train.optimize import Trainer, evaluate, expon_lr, load_model, train
from cobgs.configs import TrainConfig


def _orbit_camera(i, n, w, h, radius=3.0):
    a = 2 * math.pi * i / n
    eye = torch.tensor([radius * math.cos(a), 0.6 * math.sin(2 * a), radius * math.sin(a)])
    fwd = -eye / eye.norm()
    right = torch.linalg.cross(torch.tensor([0.0, -1.0, 0.0]), fwd)
    right = right / right.norm()
    down = torch.linalg.cross(fwd, right)
    c2w = torch.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, fwd, eye
    f = 0.9 * w
    return Camera.from_c2w(c2w, f, f, w / 2, h / 2, w, h, f"v{i:02d}")


@pytest.fixture(scope="module")
def tiny_scene():
    """12 views (every 4th held out) of 40 coloured Gaussians rendered by the rasterizer."""
    g = torch.Generator().manual_seed(0)
    n = 40
    gt = GaussianModel(
        torch.randn(n, 3, generator=g) * 0.45,
        torch.log(torch.rand(n, 3, generator=g) * 0.12 + 0.06),
        torch.randn(n, 4, generator=g),
        torch.full((n,), 2.5),
        (torch.rand(n, 1, 3, generator=g) - 0.5) * 3.0,
        torch.zeros(n, 0, 3),
    )
    views = []
    for i in range(12):
        cam = _orbit_camera(i, 12, 40, 30)
        with torch.no_grad():
            img = render(gt, cam, torch.zeros(3)).image.clamp(0, 1)
        views.append(View(cam, img, cam.name))
    scene = make_scene(views, test_every=4, kind="test")
    scene.init_bounds = ([-1.2] * 3, [1.2] * 3)
    return scene


def _cfg(**kw):
    base = dict(
        iterations=40, scale_schedule=False, random_init_points=300, sh_degree=1,
        sh_degree_interval_its=15, position_lr_decay_its=40, densify_from_its=5,
        densify_interval_its=10, densify_until_its=35, opacity_reset_interval_its=30,
        densify_grad_threshold_ndc=5e-5, log_interval_its=5,
    )
    base.update(kw)
    return TrainConfig(**base)


def test_schedule_scaling_and_lr():
    s = TrainConfig(iterations=7000).schedule()
    assert (s.densify_from, s.densify_until, s.densify_interval) == (117, 3500, 100)
    assert TrainConfig(iterations=7000, scale_densify_interval=True).schedule().densify_interval == 23
    assert (s.opacity_reset_interval, s.sh_degree_interval, s.position_lr_decay) == (700, 233, 7000)
    full = TrainConfig(iterations=7000, scale_schedule=False).schedule()
    assert (full.densify_until, full.densify_interval, full.position_lr_decay) == (15000, 100, 30000)
    assert expon_lr(0, 1.6e-4, 1.6e-6, 100) == pytest.approx(1.6e-4)
    assert expon_lr(50, 1.6e-4, 1.6e-6, 100) == pytest.approx(1.6e-5)
    assert expon_lr(500, 1.6e-4, 1.6e-6, 100) == pytest.approx(1.6e-6)
    with pytest.raises(InputError, match="sh_degree"):
        TrainConfig(sh_degree=4)


def test_tiny_scene_loss_falls_and_psnr_rises(tiny_scene):
    cfg = _cfg(iterations=300, position_lr_decay_its=300, densify_until_its=200, densify_interval_its=25,
               densify_from_its=50, opacity_reset_interval_its=10_000, sh_degree_interval_its=100)
    trainer = Trainer(tiny_scene, cfg)
    before = evaluate(trainer.model, tiny_scene.test)["psnr"]
    res = train(tiny_scene, cfg, progress=False)
    first = sum(h["loss"] for h in res.history[:4]) / 4
    last = sum(h["loss"] for h in res.history[-4:]) / 4
    assert last < 0.5 * first, (first, last)
    assert res.eval["psnr"] > 22.0 and res.eval["psnr"] > before + 8.0, (before, res.eval["psnr"])
    assert 0.0 < res.eval["ssim"] <= 1.0 and set(res.eval["per_view"]) == {v.name for v in tiny_scene.test}
    assert res.model.active_sh_degree == 1 and res.iterations == 300
    assert res.history[-1]["num_gaussians"] == len(res.model) != 300  # densification ran
    # The final Adam moments (what COB-GS's texture stages continue) follow the final model.
    assert sorted(res.adam_moments) == sorted(["means", "sh0", "shN", "opacity_logits", "log_scales", "quats"])
    for name, m in res.adam_moments.items():
        assert m["exp_avg"].shape == m["exp_avg_sq"].shape == res.model.data[name].shape, name
        assert bool((m["exp_avg_sq"] >= 0).all()), name
        # Adam counts the steps a tensor had a gradient: shN only once SH degree 1 is active.
        assert float(m["step"]) == (201 if name == "shN" else 300), name


def test_densify_and_prune_keeps_optimizer_consistent(tiny_scene):
    tr = Trainer(tiny_scene, _cfg())
    for _ in range(3):
        tr.step()
    m = tr.model
    n = len(m)
    ext = tr.extent
    # Hand-made statistics: Gaussians 0..9 hot and small (clone), 10..19 hot and big
    # (split), 20..24 transparent (prune); everything else cold.
    with torch.no_grad():
        ls = m.log_scales.detach().clone()
        ls[:10] = math.log(0.001 * ext)
        ls[10:20] = math.log(0.05 * ext)
        ls[20:] = math.log(0.001 * ext)
        m.set_tensor("log_scales", ls, [tr.optimizer], reset_state=False)
        op = m.opacity_logits.detach().clone()
        op[:] = 0.0
        op[20:25] = -8.0
        m.set_tensor("opacity_logits", op, [tr.optimizer], reset_state=False)
    tr.grad_accum.zero_()
    tr.grad_count.fill_(1)
    tr.grad_accum[:20] = 1.0
    old_state = {g["name"]: {k: v.clone() for k, v in tr.optimizer.state[g["params"][0]].items()} for g in tr.optimizer.param_groups}
    old_means = m.means.detach().clone()
    counts = tr.densify_and_prune()
    assert counts == {"cloned": 10, "split": 10, "pruned": 5}
    m = tr.model
    assert len(m) == n + 10 + 10 - 5
    # Survivors in order: originals except split parents and pruned, then clones, then children.
    keep_orig = torch.ones(n, dtype=torch.bool)
    keep_orig[10:25] = False
    n_orig = int(keep_orig.sum())
    assert torch.equal(m.means.detach()[:n_orig], old_means[keep_orig])
    assert torch.equal(m.means.detach()[n_orig : n_orig + 10], old_means[:10])  # clones: exact copies
    assert torch.allclose(m.log_scales.detach()[-20:], torch.full((20, 3), math.log(0.05 * ext / 1.6)), atol=1e-5)
    with_state = 0
    for g in tr.optimizer.param_groups:
        p = g["params"][0]
        assert p is m.data[g["name"]]
        if not old_state[g["name"]]:  # no gradient yet (shN while the SH degree is 0)
            assert g["name"] == "shN" and not tr.optimizer.state[p]
            continue
        with_state += 1
        st = tr.optimizer.state[p]
        assert st["exp_avg"].shape == p.shape and st["exp_avg_sq"].shape == p.shape
        old = old_state[g["name"]]
        assert torch.equal(st["exp_avg"][:n_orig], old["exp_avg"][keep_orig])
        assert torch.equal(st["exp_avg_sq"][:n_orig], old["exp_avg_sq"][keep_orig])
        assert torch.all(st["exp_avg"][n_orig:] == 0) and torch.all(st["exp_avg_sq"][n_orig:] == 0)
        assert torch.equal(st["step"], old["step"])
    assert with_state == 5
    assert tr.grad_accum.shape == (len(m),) and torch.all(tr.grad_accum == 0)
    for _ in range(3):  # optimisation continues on the edited model
        tr.step()
    tr.reset_opacity()
    assert torch.all(tr.model.opacities <= 0.01 + 1e-6)
    st = tr.optimizer.state[tr.model.opacity_logits]
    assert torch.all(st["exp_avg"] == 0)


def test_deterministic_and_resume_is_exact(tiny_scene, tmp_path):
    cfg = _cfg(checkpoint_interval_its=20)
    a = train(tiny_scene, cfg, checkpoint_dir=tmp_path / "a", progress=False, evaluate_test=False)
    b = train(tiny_scene, cfg, progress=False, evaluate_test=False)
    assert (tmp_path / "a" / "ckpt_20.pt").is_file() and (tmp_path / "a" / "ckpt_final.pt").is_file()
    for k in a.model.data:
        assert torch.equal(a.model.data[k], b.model.data[k]), k
    # Resume from iteration 20 (densification, an opacity reset and an SH step follow).
    c = train(tiny_scene, cfg, resume=tmp_path / "a" / "ckpt_20.pt", progress=False, evaluate_test=False)
    assert c.iterations == 40 and c.history[0]["it"] == 25
    assert len(c.model) == len(a.model)
    for k in a.model.data:
        assert torch.equal(a.model.data[k], c.model.data[k]), k
    assert c.model.active_sh_degree == a.model.active_sh_degree
    m = load_model(tmp_path / "a" / "ckpt_final.pt")
    assert all(torch.equal(m.data[k], a.model.data[k]) for k in a.model.data)
    other = _cfg(densify_grad_threshold_ndc=1e-3)
    with pytest.raises(InputError, match="densify_grad_threshold_ndc"):
        train(tiny_scene, other, resume=tmp_path / "a" / "ckpt_20.pt", progress=False)


class _Payload:
    """Unpickling this runs code: it creates a marker file."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


def test_a_crafted_checkpoint_is_refused_without_running_code(tiny_scene, tmp_path):
    """Checkpoints are read with torch.load(weights_only=True) (resume and load_model): a
    pickle carrying any other object is refused naming the file, and its code never runs."""
    marker = tmp_path / "ran"
    bad = tmp_path / "ckpt_20.pt"
    torch.save({"version": 1, "model": _Payload(marker)}, bad)
    with pytest.raises(DataError, match="refused: the checkpoint holds objects") as info:
        load_model(bad)
    assert str(bad) in str(info.value) and not marker.exists()
    with pytest.raises(DataError, match="refused") as info:
        train(tiny_scene, _cfg(), resume=bad, progress=False, evaluate_test=False)
    assert str(bad) in str(info.value) and not marker.exists()
    torch.save([1, 2], bad)
    with pytest.raises(DataError, match="not a cobgs training checkpoint"):
        load_model(bad)


def test_random_background_draws_a_colour_per_iteration_and_resumes_exactly(tiny_scene, tmp_path, monkeypatch):
    import cobgs.train.optimize as train_mod

    seen = []
    real_render = train_mod.render

    def spy(model, camera, background, **kw):
        seen.append(torch.as_tensor(background).clone())
        return real_render(model, camera, background, **kw)

    monkeypatch.setattr(train_mod, "render", spy)
    t = Trainer(tiny_scene, _cfg(random_background=True))
    for _ in range(4):
        t.step()
    bgs = torch.stack(seen)
    assert bgs.shape == (4, 3) and bool(((bgs >= 0) & (bgs <= 1)).all())
    assert len({tuple(b.tolist()) for b in bgs}) == 4  # a fresh colour each iteration
    seen.clear()
    t = Trainer(tiny_scene, _cfg())
    t.step()
    t.step()
    assert all(torch.equal(b, torch.zeros(3)) for b in seen)  # off: the scene's fixed colour
    monkeypatch.setattr(train_mod, "render", real_render)

    cfg = _cfg(random_background=True, checkpoint_interval_its=20)
    a = train(tiny_scene, cfg, checkpoint_dir=tmp_path / "a", progress=False, evaluate_test=False)
    c = train(tiny_scene, cfg, resume=tmp_path / "a" / "ckpt_20.pt", progress=False, evaluate_test=False)
    fixed = train(tiny_scene, _cfg(), progress=False, evaluate_test=False)
    for k in a.model.data:
        assert torch.equal(a.model.data[k], c.model.data[k]), k
    assert any(
        a.model.data[k].shape != fixed.model.data[k].shape or not torch.equal(a.model.data[k], fixed.model.data[k])
        for k in a.model.data
    )


def test_random_background_refuses_rgba_composited_scenes(tiny_scene):
    import dataclasses

    blender_like = dataclasses.replace(tiny_scene, kind="blender", background=(1.0, 1.0, 1.0))
    with pytest.raises(InputError, match="random_background.*composited"):
        Trainer(blender_like, _cfg(random_background=True))


def test_non_finite_training_stops_naming_the_iteration(tiny_scene, tmp_path):
    """Issue 38 H2: a loss or a parameter that becomes non-finite stops the run with the
    iteration; no result and no final checkpoint are written."""
    from cobgs.errors import DivergenceError

    scene = tiny_scene
    bad = [View(v.camera, v.image * float("nan"), v.name) for v in scene.train + scene.test]
    bad_scene = make_scene(bad, test_names=[v.name for v in scene.test], kind="test")
    bad_scene.init_bounds = scene.init_bounds
    with pytest.raises(DivergenceError, match=r"iteration 1: loss nan"):
        train(bad_scene, _cfg(), progress=False, checkpoint_dir=tmp_path)

    def poison(trainer, info):
        if trainer.iteration == 7:
            with torch.no_grad():
                trainer.model.data["log_scales"][0, 0] = float("inf")

    with pytest.raises(DivergenceError, match=r"iteration (8|9|10): (non-finite values in log_scales|loss)"):
        train(scene, _cfg(), progress=False, callback=poison, checkpoint_dir=tmp_path)
    assert not (tmp_path / "ckpt_final.pt").exists()
