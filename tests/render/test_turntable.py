"""Turntables: the orbit's geometry, the renders, the animation file."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cobgs.errors import InputError
from cobgs.render.turntable import object_center, orbit_cameras, render_turntable, write_animation
from refine_fixtures import tiny_scene


def test_orbit_looks_at_the_centre_from_the_first_cameras_height_with_up_upwards():
    model, views, _ = tiny_scene(n_views=3)
    refs = [v.camera for v in views]
    c = torch.tensor([0.1, 0.05, -0.2])
    cams = orbit_cameras(refs, c, n_frames=8, max_width=20)
    assert len(cams) == 8 and all(cam.width == 20 and cam.height == 15 for cam in cams)
    dist = [float((cam.center - c).norm()) for cam in cams]
    assert max(dist) - min(dist) < 1e-4
    up = torch.nn.functional.normalize(torch.stack([-r.c2w[:3, 1] for r in refs]).mean(0), dim=0)
    # the references span 70 degrees (a forward-facing capture): the frames sweep over that
    # range and never go round to the back
    def angle(p):
        v = p.double() - c.double()
        v = v - (v @ up.double()) * up.double()
        r0 = refs[0].center.double() - c.double()
        r0 = r0 - (r0 @ up.double()) * up.double()
        return float(torch.atan2(torch.linalg.cross(r0, v) @ up.double(), r0 @ v))
    ref_angles = [angle(r.center) for r in refs]
    cam_angles = [angle(cam.center) for cam in cams]
    assert min(ref_angles) - 1e-3 <= min(cam_angles) and max(cam_angles) <= max(ref_angles) + 1e-3
    assert max(cam_angles) - min(cam_angles) > 0.9 * (max(ref_angles) - min(ref_angles))
    # cameras all round (one more on the far side): a full circle, frame 0 at the first camera
    from cobgs.render.camera import Camera
    from cobgs.render.turntable import _look_at

    off = refs[0].center.double() - c.double()
    h = (off @ up.double()) * up.double()
    opposite = c.double() + h - (off - h)
    far = Camera(K=refs[0].K, viewmat=torch.linalg.inv(_look_at(opposite, c.double(), up.double())).float(),
                 width=refs[0].width, height=refs[0].height, name="far")
    full = orbit_cameras(refs + [far], c, n_frames=8)
    assert torch.allclose(full[0].center, refs[0].center, atol=1e-4)
    assert max(angle(cam.center) for cam in full) - min(angle(cam.center) for cam in full) > 3.0
    for cam in cams:
        uv, depth = cam.project(torch.stack([c, c + 0.3 * up]))
        assert depth[0] > 0
        assert torch.allclose(uv[0], torch.tensor([cam.width / 2, cam.height / 2]), atol=1e-3)
        assert uv[1, 1] < uv[0, 1] - 0.5  # "up" goes up the image
    with pytest.raises(InputError):
        orbit_cameras([], c)


def test_turntable_frames_show_the_object_and_the_gif_holds_them(tmp_path):
    from PIL import Image

    model, views, _ = tiny_scene(n_views=3)
    centre = object_center(model)
    cams = orbit_cameras([v.camera for v in views], centre, n_frames=6, max_width=40)
    frames = render_turntable(model, cams)
    assert len(frames) == 6 and all(f.dtype == np.uint8 and f.shape == (30, 40, 3) for f in frames)
    assert all(f[10:20, 14:26].mean() > 10 for f in frames)  # the scene is in view, not black
    assert not np.array_equal(frames[0], frames[1])  # it turns
    path = write_animation(frames, tmp_path / "t.gif")
    with Image.open(path) as im:
        assert im.n_frames == 6 and im.info.get("loop") == 0
    assert not list(tmp_path.glob("*.part"))
