"""Bring your own trained 3DGS (cobgs.data.trained3dgs): original-3DGS output folders, plain
PLYs, checkpoints read safely, and the checks that refuse a scene of other data."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from cobgs.render.camera import Camera
from cobgs.data.scene import View, make_scene
from cobgs.errors import DataError
from cobgs.gaussians.model import GaussianModel
from cobgs.gaussians.ply import save_ply
from cobgs.data.trained3dgs import check_against_scene, read_trained


def _camera(i, n, w=40, h=30):
    a = 2 * math.pi * i / n
    eye = torch.tensor([3.0 * math.cos(a), 0.3, 3.0 * math.sin(a)])
    fwd = -eye / eye.norm()
    right = torch.linalg.cross(torch.tensor([0.0, -1.0, 0.0]), fwd)
    right = right / right.norm()
    c2w = torch.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, torch.linalg.cross(fwd, right), fwd, eye
    return Camera.from_c2w(c2w, 0.9 * w, 0.9 * w, w / 2, h / 2, w, h, f"v{i:02d}")


@pytest.fixture()
def scene_and_model():
    g = torch.Generator().manual_seed(0)
    n = 200
    model = GaussianModel(torch.randn(n, 3, generator=g) * 0.4, torch.full((n, 3), -3.0),
                          torch.randn(n, 4, generator=g), torch.zeros(n),
                          torch.rand(n, 1, 3, generator=g), torch.zeros(n, 15, 3))
    views = [View(_camera(i, 8), torch.zeros(30, 40, 3), f"v{i:02d}") for i in range(8)]
    return make_scene(views, test_every=0), model


def _output_folder(root, model, scene, iteration=7000, checkpoint=True, cfg_sh=3):
    """An output folder as the original 3DGS code writes it."""
    d = root / "point_cloud" / f"iteration_{iteration}"
    d.mkdir(parents=True)
    save_ply(d / "point_cloud.ply", model)
    (root / "cfg_args").write_text(f"Namespace(data_device='cuda', eval=False, images='images', "
                                   f"model_path='{root}', resolution=-1, sh_degree={cfg_sh}, "
                                   f"source_path='/data/scene', white_background=False)")
    cams = []
    for i, v in enumerate(scene.train):
        c = v.camera
        cams.append({"id": i, "img_name": v.name, "width": c.width, "height": c.height,
                     "position": c.center.tolist(), "rotation": np.eye(3).tolist(),
                     "fy": float(c.fy), "fx": float(c.fx)})
    (root / "cameras.json").write_text(json.dumps(cams))
    moments = None
    if checkpoint:
        n = len(model)
        g = torch.Generator().manual_seed(1)
        tensors = [model.means, model.data["sh0"], model.data["shN"], model.data["opacity_logits"][:, None],
                   model.data["log_scales"], model.data["quats"]]
        names = ["xyz", "f_dc", "f_rest", "opacity", "scaling", "rotation"]
        state, groups, moments = {}, [], {}
        for k, (nm, t) in enumerate(zip(names, tensors)):
            ea, eas = torch.randn(t.shape, generator=g), torch.rand(t.shape, generator=g)
            state[k] = {"step": torch.tensor(float(iteration)), "exp_avg": ea, "exp_avg_sq": eas}
            groups.append({"params": [k], "lr": 0.001, "name": nm})
            moments[nm] = (ea, eas)
        capture = (3, model.means.detach().clone(), tensors[1].detach(), tensors[2].detach(),
                   tensors[4].detach(), tensors[5].detach(), tensors[3].detach(), torch.zeros(n),
                   torch.zeros(n, 1), torch.zeros(n, 1), {"state": state, "param_groups": groups}, 1.0)
        torch.save((capture, iteration), root / f"chkpnt{iteration}.pth")
    return moments


def test_3dgs_output_folder_with_checkpoint(tmp_path, scene_and_model):
    scene, model = scene_and_model
    saved = _output_folder(tmp_path, model, scene)
    imp = read_trained(tmp_path)
    assert imp.source["kind"] == "3dgs_output" and imp.source["iteration"] == 7000
    assert imp.source["cfg_args"]["sh_degree"] == 3 and imp.source["checkpoint"].endswith("chkpnt7000.pth")
    assert torch.equal(imp.model.means, model.means)
    # the optimizer state arrives under the model's names, shaped like its tensors
    assert torch.equal(imp.moments["opacity_logits"]["exp_avg"], saved["opacity"][0][:, 0])
    assert torch.equal(imp.moments["shN"]["exp_avg_sq"], saved["f_rest"][1])
    assert float(imp.moments["means"]["step"]) == 7000.0
    checks = check_against_scene(imp, scene)
    assert checks["visible_fraction"] > 0.9 and checks["cameras_matched"] == 8


def test_highest_or_named_iteration_and_no_checkpoint(tmp_path, scene_and_model):
    scene, model = scene_and_model
    _output_folder(tmp_path, model, scene, iteration=7000, checkpoint=False)
    d = tmp_path / "point_cloud" / "iteration_30000"
    d.mkdir()
    save_ply(d / "point_cloud.ply", model)
    imp = read_trained(tmp_path)
    assert imp.source["iteration"] == 30000 and imp.moments is None
    assert any("zero Adam moments" in n for n in imp.notes)
    assert read_trained(tmp_path, 7000).source["iteration"] == 7000
    with pytest.raises(DataError, match=r"no iteration 5 \(saved iterations: \[7000, 30000\]\)"):
        read_trained(tmp_path, 5)


def test_a_ply_of_another_scene_is_refused(tmp_path, scene_and_model):
    """Out of every camera's view (50 units above the ring of cameras) ..."""
    scene, model = scene_and_model
    far = GaussianModel(model.means.detach() + torch.tensor([0.0, 50.0, 0.0]), model.log_scales.detach(),
                        model.quats.detach(), model.opacity_logits.detach(), model.data["sh0"].detach(),
                        model.data["shN"].detach())
    save_ply(tmp_path / "other.ply", far)
    imp = read_trained(tmp_path / "other.ply")
    with pytest.raises(DataError, match="does not belong to this scene") as info:
        check_against_scene(imp, scene)
    assert "other.ply" in str(info.value)


def test_a_ply_away_from_the_sfm_points_is_refused(tmp_path, scene_and_model):
    """... or in view but away from the scene's SfM points (another world frame along the
    view direction of some camera)."""
    scene, model = scene_and_model
    scene.points = model.means.detach().clone()
    imp = read_trained(_save(tmp_path / "same.ply", model))
    assert check_against_scene(imp, scene)["median_distance_to_sfm_points_of_diagonal"] == 0.0
    shifted = GaussianModel(model.means.detach() + torch.tensor([0.0, 0.0, 40.0]), model.log_scales.detach(),
                            model.quats.detach(), model.opacity_logits.detach(), model.data["sh0"].detach(),
                            model.data["shN"].detach())
    with pytest.raises(DataError, match="away from the scene's SfM points") as info:
        check_against_scene(read_trained(_save(tmp_path / "shifted.ply", shifted)), scene)
    assert "shifted.ply" in str(info.value)


def _save(path, model):
    save_ply(path, model)
    return path


def test_cameras_json_of_other_poses_is_refused(tmp_path, scene_and_model):
    scene, model = scene_and_model
    _output_folder(tmp_path, model, scene, checkpoint=False)
    cams = json.loads((tmp_path / "cameras.json").read_text())
    cams[3]["position"] = [p + 0.5 for p in cams[3]["position"]]
    (tmp_path / "cameras.json").write_text(json.dumps(cams))
    with pytest.raises(DataError, match="camera centres in cameras.json differ") as info:
        check_against_scene(read_trained(tmp_path), scene)
    assert "cameras.json" in str(info.value)


def test_cfg_args_sh_degree_must_match_the_ply(tmp_path, scene_and_model):
    scene, model = scene_and_model
    _output_folder(tmp_path, model, scene, checkpoint=False, cfg_sh=1)
    with pytest.raises(DataError, match="cfg_args says sh_degree=1") as info:
        read_trained(tmp_path)
    assert "cfg_args" in str(info.value)


class _Payload:
    """A pickled object that would create a file when unpickled by a trusting loader."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


def test_a_crafted_checkpoint_is_never_unpickled(tmp_path, scene_and_model):
    scene, model = scene_and_model
    _output_folder(tmp_path, model, scene, checkpoint=False)
    marker = tmp_path / "pwned"
    torch.save((_Payload(marker), 7000), tmp_path / "chkpnt7000.pth")
    with pytest.raises(DataError, match=r"weights_only=True") as info:
        read_trained(tmp_path)
    assert "chkpnt7000.pth" in str(info.value) and not marker.exists()


def test_a_checkpoint_of_another_iteration_is_refused(tmp_path, scene_and_model):
    scene, model = scene_and_model
    _output_folder(tmp_path, model, scene)
    moved = GaussianModel(model.means.detach() + 0.01, model.log_scales.detach(), model.quats.detach(),
                          model.opacity_logits.detach(), model.data["sh0"].detach(), model.data["shN"].detach())
    save_ply(tmp_path / "point_cloud" / "iteration_7000" / "point_cloud.ply", moved)
    with pytest.raises(DataError, match="different iterations"):
        read_trained(tmp_path)


@pytest.mark.parametrize("field, value", [("position", [1.0, 2.0]), ("fx", 0.0), ("width", 0)])
def test_cameras_json_with_unusable_values_is_refused(tmp_path, scene_and_model, field, value):
    scene, model = scene_and_model
    _output_folder(tmp_path, model, scene, checkpoint=False)
    cams = json.loads((tmp_path / "cameras.json").read_text())
    cams[2][field] = value
    (tmp_path / "cameras.json").write_text(json.dumps(cams))
    with pytest.raises(DataError, match="camera 'v02': expected a finite 3-vector") as info:
        read_trained(tmp_path)
    assert "cameras.json" in str(info.value)


@pytest.mark.parametrize("damage, what", [
    (lambda st: st.pop("exp_avg"), "not Adam state"),
    (lambda st: st.update(exp_avg_sq=torch.full_like(st["exp_avg_sq"], float("nan"))), "non-finite"),
])
def test_a_checkpoint_with_damaged_adam_state_is_refused(tmp_path, scene_and_model, damage, what):
    scene, model = scene_and_model
    _output_folder(tmp_path, model, scene)
    ck = tmp_path / "chkpnt7000.pth"
    capture, it = torch.load(ck, weights_only=True)
    damage(capture[10]["state"][3])
    torch.save((capture, it), ck)
    with pytest.raises(DataError, match=what) as info:
        read_trained(tmp_path)
    assert "chkpnt7000.pth" in str(info.value)


@pytest.mark.parametrize("damage, words", [
    ("scales", "100.0% have a scale over 100 scene extents"),
    ("quats", "100.0% have a zero rotation"),
    ("half_quats", "50.0% have a zero rotation"),
])
def test_degenerate_gaussians_are_named_with_their_fraction(tmp_path, scene_and_model, damage, words):
    """Issue 44 L7: a PLY with every scale exp(80) or every rotation zero imported and ran to
    "done" with IoU 0, silently. The check warns, naming the fraction (the stage's task warning)."""
    scene, model = scene_and_model
    ls, q = model.log_scales.detach().clone(), model.quats.detach().clone()
    if damage == "scales":
        ls[:] = 80.0
    elif damage == "quats":
        q[:] = 0.0
    else:
        q[: len(q) // 2] = 0.0
    bad = GaussianModel(model.means.detach(), ls, q, model.opacity_logits.detach(), model.data["sh0"].detach(),
                        model.data["shN"].detach())
    save_ply(tmp_path / "bad.ply", bad)
    checks = check_against_scene(read_trained(tmp_path / "bad.ply"), scene)
    assert words in checks["warning"] and f"of its {len(model)} Gaussians" in checks["warning"], checks
    save_ply(tmp_path / "good.ply", model)
    good = check_against_scene(read_trained(tmp_path / "good.ply"), scene)
    assert good["warning"] == "" and good["degenerate"] == {"zero_rotation": 0.0, "huge_scale": 0.0,
                                                            "non_finite": 0.0}
