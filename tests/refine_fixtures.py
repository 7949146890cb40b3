"""Small deterministic scenes for the refinement, segmentation and peer tests (no tests here).

``tiny_scene``: random Gaussians in a cube seen by a few cameras on an arc; two
"objects" are analytic spheres, their GT masks are the exact pixel-ray / sphere hits, the
images are renders of the Gaussians themselves (so the texture loss starts low).
``three_gaussians``: one camera and three Gaussians with hand-known label statistics.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from cobgs.render.camera import Camera
from cobgs.data.scene import View
from cobgs.gaussians.model import GaussianModel
from cobgs.render.image import render_image

SPHERES = {"ball": ((-0.35, 0.0, 0.0), 0.45), "cube": ((0.45, 0.1, 0.1), 0.3)}


def look_at_camera(eye, target, width: int, height: int, f: float, name: str) -> Camera:
    """OpenCV camera at ``eye`` looking at ``target`` (world +y is "up" on screen)."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    z /= np.linalg.norm(z)
    up = np.array([0.0, -1.0, 0.0])  # OpenCV +y points down
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = x, y, z, eye
    return Camera.from_c2w(c2w, f, f, width / 2, height / 2, width, height, name=name)


def sphere_mask(camera: Camera, center, radius: float) -> torch.Tensor:
    """[H, W] bool: pixel-centre rays that hit the sphere."""
    H, W = camera.height, camera.width
    j, i = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64),
                          indexing="ij")
    d_cam = torch.stack([(i + 0.5 - camera.cx) / camera.fx, (j + 0.5 - camera.cy) / camera.fy,
                         torch.ones_like(i)], -1)
    c2w = camera.c2w.double()
    d = d_cam @ c2w[:3, :3].T
    d = d / d.norm(dim=-1, keepdim=True)
    o = c2w[:3, 3]
    oc = o - torch.tensor(center, dtype=torch.float64)
    b = (d * oc).sum(-1)
    c = (oc * oc).sum() - radius**2
    return (b * b - c) > 0


def tiny_model(n: int = 600, seed: int = 0) -> GaussianModel:
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) * 2 - 1) * torch.tensor([1.0, 0.7, 0.7])
    log_scales = torch.log(torch.full((n, 3), 0.06) * torch.exp(0.3 * torch.randn(n, 3, generator=g)))
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1)
    opac = torch.full((n,), 1.5)
    inside = torch.zeros(n, dtype=torch.bool)
    for c, r in SPHERES.values():
        inside |= (means - torch.tensor(c)).norm(dim=-1) < r
    rgb = torch.where(inside[:, None], torch.tensor([0.9, 0.2, 0.1]), torch.tensor([0.1, 0.3, 0.8]))
    rgb = (rgb + 0.1 * torch.rand(n, 3, generator=g)).clamp(0, 1)
    sh0 = ((rgb - 0.5) / 0.28209479177387814)[:, None, :]
    shN = torch.zeros(n, 3, 3)
    return GaussianModel(means, log_scales, quats, opac, sh0, shN)


def tiny_scene(n_views: int = 5, width: int = 40, height: int = 30, n: int = 600, seed: int = 0):
    """(model, views, extent): views on an arc at distance 3.2 around the origin."""
    model = tiny_model(n, seed)
    views = []
    for k in range(n_views):
        a = math.radians(-35 + 70 * k / max(1, n_views - 1))
        eye = (3.2 * math.sin(a), -0.3, -3.2 * math.cos(a))
        cam = look_at_camera(eye, (0.0, 0.0, 0.0), width, height, 0.9 * width, f"v{k}")
        img = render_image(model, cam).clamp(0, 1)
        masks = {name: sphere_mask(cam, c, r) for name, (c, r) in SPHERES.items()}
        views.append(View(camera=cam, image=img, name=f"v{k}", masks=masks))
    return model, views, 3.0


def three_gaussians():
    """One 32x32 camera (identity pose, f = 50) and three Gaussians:

    A at x = −0.3, z = 2: fully inside the GT object (left half, columns < 16): N⁻ = 0;
    B at x = 0, z = 2: centred on the mask edge, mirror-symmetric: N⁺ = N⁻;
    C behind the camera: never contributes (unseen).
    """
    W = H = 32
    cam = Camera(K=torch.tensor([[50.0, 0, 16.0], [0, 50.0, 16.0], [0, 0, 1]]), viewmat=torch.eye(4),
                 width=W, height=H, name="cam")
    means = torch.tensor([[-0.3, 0.0, 2.0], [0.0, 0.0, 2.0], [0.0, 0.0, -2.0]])
    log_scales = torch.log(torch.tensor([[0.02] * 3, [0.05] * 3, [0.05] * 3]))
    quats = torch.tensor([[1.0, 0, 0, 0]] * 3)
    opac = torch.full((3,), 0.0)  # opacity 0.5
    sh0 = torch.zeros(3, 1, 3)
    model = GaussianModel(means, log_scales, quats, opac, sh0, torch.zeros(3, 0, 3))
    mask = torch.zeros(H, W, dtype=torch.bool)
    mask[:, :16] = True
    view = View(camera=cam, image=torch.zeros(H, W, 3), name="cam", masks={"obj": mask})
    return model, view


def synthetic_surface_points(preset: str, seed: int, views, n_points: int, rng_seed: int = 0, **overrides):
    """Surface points of a synthetic scene seen by ``views``: the "perfect SfM" start.

    Rays through random pixels of the training views are cast against the generator's
    exact geometry (:func:`cobgs.data.synth.render.make_caster`); each hit becomes a
    point coloured by the image pixel it came from. ``preset``, ``seed`` and
    ``overrides`` (e.g. ``width_px``) must be those the scene was generated with.

    Returns:
        (xyz [P, 3] float32, rgb [P, 3] float32), P <= n_points (misses dropped).
    """
    from cobgs.data.synth.render import make_caster
    from cobgs.data.synth.scene import build_scene

    _, geometry, _ = build_scene(preset, seed, **overrides)
    caster = make_caster(geometry)
    g = np.random.default_rng(rng_seed)
    per_view = int(math.ceil(n_points / len(views)))
    xyz, rgb = [], []
    for v in views:
        cam = v.camera
        px = g.random((per_view, 2)) * np.array([cam.width, cam.height])
        d_cam = np.stack([(px[:, 0] - cam.cx) / cam.fx, (px[:, 1] - cam.cy) / cam.fy, np.ones(per_view)], 1)
        c2w = cam.c2w.double().numpy()
        d = d_cam @ c2w[:3, :3].T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        o = c2w[:3, 3]
        t, which = caster.first_hit(o, d)
        ok = np.isfinite(t) & (which >= 0)
        xyz.append(o + t[ok, None] * d[ok])
        ij = np.floor(px[ok]).astype(int)
        rgb.append(v.image.numpy()[ij[:, 1], ij[:, 0]])
    return (torch.from_numpy(np.concatenate(xyz)[:n_points]).float(),
            torch.from_numpy(np.concatenate(rgb)[:n_points]).float())
