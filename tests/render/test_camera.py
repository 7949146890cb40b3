"""Camera model: pose conventions, intrinsics scaling, extent."""

import math

import numpy as np
import pytest
import torch

from cobgs.render.camera import Camera, scene_extent
from cobgs.errors import InputError


def _look_at_gl(eye, target):
    """camera→world in OpenGL axes (+y up, camera looks down -z)."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    back = eye - target
    back /= np.linalg.norm(back)
    right = np.cross([0.0, 0.0, 1.0], back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, up, back, eye
    return m


def test_opengl_pose_projects_target_to_principal_point():
    cam = Camera.from_c2w(_look_at_gl([3, 1, 2], [0, 0, 0]), 100, 100, 40, 30, 80, 60, opengl=True)
    uv, z = cam.project(torch.zeros(1, 3))
    assert torch.allclose(uv, torch.tensor([[40.0, 30.0]]), atol=1e-4)
    assert z.item() == pytest.approx(math.sqrt(14), rel=1e-5)  # in front, positive depth
    assert torch.allclose(cam.center, torch.tensor([3.0, 1.0, 2.0]), atol=1e-5)
    # World "up" (+z here) must appear above the target, i.e. at a smaller row (OpenCV +y down).
    uv_up, _ = cam.project(torch.tensor([[0.0, 0.0, 0.5]]))
    assert uv_up[0, 1] < 30.0


def test_scaled_keeps_projection_consistent():
    cam = Camera.from_c2w(np.eye(4), 200, 210, 101, 77, 200, 150)
    half = cam.scaled(2)
    assert (half.width, half.height) == (100, 75)
    pts = torch.tensor([[0.3, -0.2, 2.0], [0.0, 0.0, 5.0]])
    uv, _ = cam.project(pts)
    uv2, _ = half.project(pts)
    assert torch.allclose(uv2, uv / 2, atol=1e-4)  # same continuous point, pixel centres at +0.5
    assert half.fov_x_rad == pytest.approx(cam.fov_x_rad, rel=1e-6)


def test_scaled_keeps_device_and_dtype():
    """The resolution schedule scales cameras that live on the GPU: the scale matrix follows
    K's device and dtype (the meta device stands in for CUDA here; it failed on an H100 when
    the matrix was always a CPU float32 tensor)."""
    cam = Camera.from_c2w(np.eye(4), 200, 210, 101, 77, 200, 150)
    meta = cam.to("meta").scaled(1.5)
    assert meta.K.device.type == "meta" and (meta.width, meta.height) == (133, 100)
    f64 = Camera(K=cam.K.double(), viewmat=cam.viewmat.double(), width=cam.width, height=cam.height)
    assert f64.scaled(2).K.dtype == torch.float64


def test_scene_extent_is_nerfpp_radius():
    centers = [(-1, 0, 0), (3, 0, 0), (1, 2, 0)]
    cams = []
    for c in centers:
        m = np.eye(4)
        m[:3, 3] = c
        cams.append(Camera.from_c2w(m, 10, 10, 5, 5, 10, 10))
    # mean centre (1, 2/3, 0); farthest camera at distance sqrt(4 + 4/9)
    assert scene_extent(cams) == pytest.approx(1.1 * math.sqrt(4 + 4 / 9), rel=1e-6)


def test_bad_camera_raises():
    with pytest.raises(InputError, match="K"):
        Camera(torch.eye(2), torch.eye(4), 10, 10)
    with pytest.raises(InputError, match="width"):
        Camera(torch.eye(3), torch.eye(4), 0, 10)
    with pytest.raises(InputError, match="c2w"):
        Camera.from_c2w(np.eye(3), 1, 1, 0, 0, 1, 1)
