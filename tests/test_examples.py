"""The library example runs as a user would run it (issue 39): a trained scene and masks
in, the object's PLY and held-out masks out, the object where its ground truth is."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]


def test_segment_object_example(tmp_path):
    from cobgs.data.readers import read_scene
    from cobgs.data.synth.scene import generate_scene
    from cobgs.gaussians.model import GaussianModel
    from cobgs.gaussians.ply import load_ply, save_ply
    from cobgs.train.optimize import train
    from cobgs.configs import TrainConfig
    from refine_fixtures import synthetic_surface_points  # tests/ is on sys.path

    size = dict(width_px=128, height_px=96, num_views=24)
    folder = generate_scene(tmp_path / "scene", "demo", seed=0, workers=1, progress=False, **size)
    scene = read_scene(folder)
    xyz, rgb = synthetic_surface_points("demo", 0, scene.train, 6000, **size)  # "perfect SfM" points
    cfg = TrainConfig(iterations=500, sh_degree=1, max_gaussians=15000, scale_densify_interval=True)
    model = train(scene, cfg, model=GaussianModel.from_points(xyz, rgb, sh_degree=1), progress=False,
                  evaluate_test=False).model
    save_ply(tmp_path / "scene.ply", model)
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, str(REPO / "examples" / "segment_object.py"), str(folder),
                        str(tmp_path / "scene.ply"), "ball", "--out", str(out), "--stage-length", "1",
                        "--scene-type", "forward"], capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "Gaussians are 'ball'" in r.stdout
    obj = load_ply(out / "object.ply")
    assert 0 < len(obj) < len(load_ply(tmp_path / "scene.ply"))
    ious = []
    for v in scene.test:
        pred = cv2.imread(str(out / f"{v.name}.png"), cv2.IMREAD_GRAYSCALE) > 127
        gt = v.masks["ball"].numpy()
        if gt.any():
            ious.append((pred & gt).sum() / (pred | gt).sum())
    assert ious and np.mean(ious) > 0.6, ious
