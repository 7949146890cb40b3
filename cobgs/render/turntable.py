"""Turntables: a short orbit around a segmented object, rendered by our rasterizer.

The orbit is a circle around the object's centre (the median of its Gaussians' means)
about the scene's up axis (the mean "up" of the reference cameras: minus their image y
axis), at the first reference camera's distance and height above the centre, with that
camera's intrinsics scaled to ``max_width``. Every frame looks at the centre. When the
reference cameras see the centre from less than half a turn (a forward-facing capture), the
frames sweep back and forth over the cameras' own angular range, where the scene was seen,
instead of going round to its unseen back. Frames are
uint8 RGB; :func:`write_animation` stores them as an animated GIF (PIL), which browsers
and file managers play without a plug-in.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from cobgs.render.camera import Camera
from cobgs.errors import InputError
from cobgs.gaussians.model import GaussianModel


def object_center(model: GaussianModel) -> Tensor:
    """[3] median of the Gaussians' means (robust to a few stray ones)."""
    if len(model) == 0:
        raise InputError("the object has no Gaussians: nothing to orbit")
    return model.data["means"].detach().float().median(dim=0).values


def _look_at(eye: Tensor, target: Tensor, up: Tensor) -> Tensor:
    """[4, 4] camera→world, OpenCV axes (x right, y down, z forward), looking at ``target``."""
    z = torch.nn.functional.normalize(target - eye, dim=0)
    down = -(up - (up @ z) * z)
    y = torch.nn.functional.normalize(down, dim=0)
    x = torch.linalg.cross(y, z)
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = x, y, z, eye
    return c2w


def orbit_cameras(reference: Sequence[Camera], center: Tensor, n_frames: int = 36,
                  max_width: int = 320) -> list[Camera]:
    """``n_frames`` cameras on the orbit described in the module docstring."""
    if not reference:
        raise InputError("an orbit needs at least one reference camera")
    if n_frames < 1:
        raise InputError(f"n_frames must be >= 1, got {n_frames}")
    c = center.double().cpu()
    ups = torch.stack([-cam.c2w.double()[:3, 1] for cam in reference])
    up = torch.nn.functional.normalize(ups.mean(0), dim=0)
    ref = reference[0]
    offset = ref.center.double() - c
    height = offset @ up
    radial = offset - height * up
    radius = float(radial.norm())
    if radius < 1e-9:  # the first camera sits on the axis: start from any perpendicular
        radial = torch.linalg.cross(up, torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
        if float(radial.norm()) < 1e-6:
            radial = torch.linalg.cross(up, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
        radius = max(float(offset.norm()), 1e-3)
    e1 = torch.nn.functional.normalize(radial, dim=0)
    e2 = torch.linalg.cross(up, e1)
    # the reference cameras' angles about the axis, relative to the first one's (in (-pi, pi])
    rel = torch.stack([cam.center.double() - c for cam in reference])
    angles = torch.atan2(rel @ e2, rel @ e1)
    lo, hi = float(angles.min()), float(angles.max())
    sweep = hi - lo < math.pi  # seen from less than half a turn: stay where it was seen
    scale = min(1.0, max_width / ref.width)
    w, h = max(1, int(round(ref.width * scale))), max(1, int(round(ref.height * scale)))
    base = ref.resized(w, h)
    cams = []
    for i in range(n_frames):
        if sweep:  # a loop lo -> hi in n//2 steps, back in the rest: no two consecutive frames alike
            m = n_frames // 2
            frac = 0.5 if m == 0 else (i / m if i <= m else (n_frames - i) / (n_frames - m))
            a = lo + (hi - lo) * frac
        else:
            a = 2.0 * math.pi * i / n_frames
        eye = c + height * up + radius * (math.cos(a) * e1 + math.sin(a) * e2)
        w2c = torch.linalg.inv(_look_at(eye, c, up)).float()
        cams.append(Camera(K=base.K.clone(), viewmat=w2c, width=w, height=h, name=f"orbit_{i:03d}"))
    return cams


def render_turntable(model: GaussianModel, cameras: Sequence[Camera], background=(0.0, 0.0, 0.0),
                     backend: str = "native") -> list[np.ndarray]:
    """uint8 [H, W, 3] frames of ``model`` seen from ``cameras``."""
    from cobgs.render.image import render_image

    bg = torch.as_tensor(background, dtype=torch.float32)
    frames = []
    for cam in cameras:
        img = render_image(model, cam, bg, backend=backend).clamp(0, 1)
        frames.append((img.cpu().numpy() * 255.0 + 0.5).astype(np.uint8))
    return frames


def write_animation(frames: Sequence[np.ndarray], path: Path, frame_ms: int = 80) -> Path:
    """An endlessly looping animated GIF of ``frames`` (written beside, then renamed)."""
    from PIL import Image

    if not frames:
        raise InputError("no frames to write")
    path = Path(path)
    tmp = path.with_name(path.name + ".part")
    images = [Image.fromarray(f) for f in frames]
    images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:], duration=frame_ms, loop=0,
                   optimize=False)
    tmp.replace(path)
    return path


def object_turntables(object_ply: Path, background_ply: Path, cameras: Sequence[Camera], background,
                      frames: int, dst: dict) -> list[str]:
    """Orbit GIFs of a segmented object alone (``object_ply``) and of the scene without it
    (``background_ply``), around the object's centre, with cameras like ``cameras``. ``dst``
    maps "object" / "removed" to the GIF paths; returns the kinds written (none when the
    object PLY is missing or empty)."""
    from cobgs.gaussians.ply import load_ply

    if not Path(object_ply).is_file():
        return []
    obj = load_ply(object_ply)
    if len(obj) == 0:
        return []
    cams = orbit_cameras(cameras, object_center(obj), n_frames=frames)
    written = []
    for kind, model in (("object", obj), ("removed", load_ply(background_ply))):
        Path(dst[kind]).parent.mkdir(parents=True, exist_ok=True)
        write_animation(render_turntable(model, cams, background), Path(dst[kind]))
        written.append(kind)
    return written
