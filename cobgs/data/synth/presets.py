"""The scenes of the synthetic presets: layouts, textures, lights and capture paths.

Layouts are built constructively so that the contacts the benchmark relies on hold for
every seed: boxes rest on the ground (a rotated box on its lowest corner), a ball rests
on a box top or leans on a box face, cylinders stand on the ground. The seed changes
colours, texture lattices, box yaws and camera jitter, never the contacts.
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass
from typing import Callable, Dict, List, Tuple

import numpy as np

from cobgs.errors import InputError
from cobgs.data.synth.cameras import forward_facing, orbit
from cobgs.data.synth.primitives import Box, Cylinder, Plane, Sphere, rotation_from_euler_deg
from cobgs.data.synth.render import SynthScene, SceneObject
from cobgs.data.synth.textures import Texture


@dataclass(frozen=True)
class SynthPreset:
    """Image size and capture of a preset (the scene itself comes from its builder).

    Attributes:
        name: preset name.
        trajectory: "forward" (LLFF-like) or "orbit" (360 degrees).
        width_px, height_px: image size.
        num_views: number of views.
        supersampling: s, an s x s grid of subsamples per pixel.
        hfov_deg: horizontal field of view.
        test_every: every n-th view (index % n == 0) is held out as a test view.
    """

    name: str
    trajectory: str
    width_px: int
    height_px: int
    num_views: int
    supersampling: int
    hfov_deg: float
    test_every: int = 8

    def __post_init__(self) -> None:
        if self.trajectory not in ("forward", "orbit"):
            raise InputError(f"trajectory must be 'forward' or 'orbit', got {self.trajectory!r}")
        for field in ("width_px", "height_px", "num_views", "supersampling", "test_every"):
            v = getattr(self, field)
            if not isinstance(v, int) or v < 1:
                raise InputError(f"preset {field} must be a positive int, got {v!r}")
        if self.width_px < 16 or self.height_px < 16:
            raise InputError(f"image must be at least 16x16 px, got {self.width_px}x{self.height_px}")


PRESETS: Dict[str, SynthPreset] = {
    "demo": SynthPreset("demo", "forward", 160, 120, 24, 3, 55.0),
    "forward": SynthPreset("forward", "forward", 400, 300, 30, 3, 55.0),
    "orbit": SynthPreset("orbit", "orbit", 400, 300, 48, 3, 60.0),
}


def _hsv(h: float, s: float, v: float) -> Tuple[float, float, float]:
    return tuple(float(c) for c in colorsys.hsv_to_rgb(h % 1.0, s, v))  # type: ignore[return-value]


def _pair(rng: np.random.Generator) -> Tuple[Tuple[float, float, float], ...]:
    """A light and a dark colour of nearby hues: strong luminance contrast for SIFT."""
    h = rng.random()
    return (_hsv(h, 0.55, 0.92), _hsv(h + rng.uniform(-0.08, 0.08), 0.75, 0.38))


def _tex_seed(rng: np.random.Generator) -> int:
    return int(rng.integers(0, 2**31 - 1))


def _ground(rng: np.random.Generator, scale: float = 0.22) -> SceneObject:
    base = _hsv(0.1 + 0.05 * rng.random(), 0.25, 0.8)
    dots = tuple(_hsv(rng.random(), 0.7, v) for v in (0.3, 0.45, 0.6))
    return SceneObject("ground", 0, Plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0)),
                       Texture("dots", (base,) + dots, scale, grain=0.35, seed=_tex_seed(rng)),
                       target=False)


def _wall(name: str, point, normal, tangent, rng: np.random.Generator) -> SceneObject:
    h = rng.random()
    cols = (_hsv(h, 0.3, 0.85), _hsv(h + 0.1, 0.6, 0.4), _hsv(h + 0.5, 0.6, 0.7))
    return SceneObject(name, 0, Plane(point, normal, tangent),
                       Texture("noise", cols, 0.2, grain=0.3, seed=_tex_seed(rng)), target=False)


def _crate(rng, oid: int, xy, half, yaw_deg: float, name: str = "crate") -> SceneObject:
    rot = rotation_from_euler_deg(yaw_deg)
    shape = Box((float(xy[0]), float(xy[1]), float(half[2])), tuple(half), rot)
    return SceneObject(name, oid, shape,
                       Texture("checker", _pair(rng), 0.11, grain=0.2, seed=_tex_seed(rng)))


def _ball_on_top(rng, oid: int, box: Box, radius: float, name: str) -> SceneObject:
    """A sphere resting on the (horizontal) top face of a yaw-only box."""
    c = (box.center[0], box.center[1], box.center[2] + box.half_extents[2] + radius)
    return SceneObject(name, oid, Sphere(c, radius),
                       Texture("noise", _pair(rng) + (_hsv(rng.random(), 0.8, 0.8),), 0.12,
                               grain=0.15, seed=_tex_seed(rng)))


def _ball_leaning(rng, oid: int, box: Box, radius: float, axis: int, side: float, name: str,
                  along: float = 0.0) -> SceneObject:
    """A sphere on the ground touching a vertical face of a yaw-only box.

    The face is the box's local ``side * axis`` face (axis 0 or 1); ``along`` shifts the
    contact point sideways on that face, as a fraction of its half width.
    """
    r = np.asarray(box.rotation)
    other = 1 - axis
    if abs(along) > 0.9 or radius > 2 * box.half_extents[2]:
        raise InputError("leaning ball would miss the box face it should touch")
    xy = (np.asarray(box.center[:2]) + r[:2, axis] * side * (box.half_extents[axis] + radius)
          + r[:2, other] * along * box.half_extents[other])
    return SceneObject(name, oid, Sphere((float(xy[0]), float(xy[1]), radius), radius),
                       Texture("dots", (_hsv(rng.random(), 0.4, 0.9), _hsv(rng.random(), 0.8, 0.35),
                                        _hsv(rng.random(), 0.8, 0.55)), 0.09, grain=0.1,
                               seed=_tex_seed(rng)))


def _can(rng, oid: int, xy, radius: float, height: float, period: float, name: str) -> SceneObject:
    return SceneObject(name, oid, Cylinder((float(xy[0]), float(xy[1]), 0.0), (0.0, 0.0, 1.0),
                                           radius, height),
                       Texture("stripes", _pair(rng), period, grain=0.15, seed=_tex_seed(rng)))


def _gem(rng, oid: int, xy, half: float, target: bool, name: str = "gem") -> SceneObject:
    """A cube at an arbitrary rotation, lowered until its lowest corner touches the ground."""
    rot = rotation_from_euler_deg(rng.uniform(0, 90), rng.uniform(25, 55), rng.uniform(15, 45))
    probe = Box((0.0, 0.0, 0.0), (half, half, half), rot)
    z = -probe.lowest_z()
    return SceneObject(name, oid, Box((float(xy[0]), float(xy[1]), z), (half, half, half), rot),
                       Texture("dots", (_hsv(rng.random(), 0.3, 0.95), _hsv(rng.random(), 0.9, 0.4)),
                               0.07, grain=0.2, seed=_tex_seed(rng)), target=target)


_LIGHT = (-0.45, -0.8, 1.25)  # from front-left, above: shadows fall behind, on ground/wall


def _demo(rng: np.random.Generator, p: SynthPreset):
    ground = _ground(rng)
    wall = _wall("back_wall", (0.0, 1.3, 0.0), (0.0, -1.0, 0.0), (1.0, 0.0, 0.0), rng)
    crate = _crate(rng, 1, (-0.2, 0.25), (0.32, 0.26, 0.26), 20.0 + rng.uniform(-8, 8))
    ball = _ball_leaning(rng, 2, crate.shape, 0.2, 1, -1.0, "ball", along=0.45)
    can = _can(rng, 3, (-0.5, -0.22), 0.13, 0.5, 0.09, "can")
    scene = SynthScene((crate, ball, can), (ground, wall), _LIGHT, ambient=0.4)
    poses = forward_facing(p.num_views, (0.0, -1.75, 0.85), (-0.05, 0.25, 0.3), 0.4, 0.22, rng)
    return scene, poses


def _forward(rng: np.random.Generator, p: SynthPreset):
    ground = _ground(rng, 0.18)
    wall = _wall("back_wall", (0.0, 1.4, 0.0), (0.0, -1.0, 0.0), (1.0, 0.0, 0.0), rng)
    crate = _crate(rng, 1, (-0.2, 0.3), (0.3, 0.24, 0.22), 25.0 + rng.uniform(-8, 8))
    ball = _ball_on_top(rng, 2, crate.shape, 0.17, "ball")
    can = _can(rng, 3, (-0.6, -0.2), 0.12, 0.55, 0.08, "can")
    pole = _can(rng, 4, (0.45, 0.05), 0.018, 1.0, 0.1, "pole")
    ball2 = _ball_leaning(rng, 5, crate.shape, 0.14, 1, -1.0, "ball2", along=0.55)
    gem = _gem(rng, 6, (0.75, -0.3), 0.12, target=False)
    scene = SynthScene((crate, ball, can, pole, ball2, gem), (ground, wall), _LIGHT, ambient=0.4)
    poses = forward_facing(p.num_views, (0.05, -2.2, 1.0), (0.05, 0.2, 0.3), 0.5, 0.28, rng)
    return scene, poses


def _orbit(rng: np.random.Generator, p: SynthPreset):
    ground = _ground(rng, 0.2)
    walls = []
    for k, (n, t) in enumerate(((( -1.0, 0.0, 0.0), (0.0, 1.0, 0.0)), ((1.0, 0.0, 0.0), (0.0, -1.0, 0.0)),
                                ((0.0, -1.0, 0.0), (1.0, 0.0, 0.0)), ((0.0, 1.0, 0.0), (-1.0, 0.0, 0.0)))):
        point = tuple(-2.8 * v for v in n)
        walls.append(_wall(f"wall_{k}", point, n, t, rng))
    crate = _crate(rng, 1, (0.05, 0.1), (0.3, 0.22, 0.22), rng.uniform(0, 90))
    ball = _ball_on_top(rng, 2, crate.shape, 0.16, "ball")
    ball2 = _ball_leaning(rng, 3, crate.shape, 0.15, 0, -1.0, "ball2")
    can = _can(rng, 4, (0.45, -0.45), 0.12, 0.5, 0.08, "can")
    pole = _can(rng, 5, (-0.35, -0.4), 0.018, 0.9, 0.1, "pole")
    gem = _gem(rng, 6, (0.5, 0.6), 0.12, target=False)
    scene = SynthScene((crate, ball, ball2, can, pole, gem), (ground, *walls), (-0.5, -0.3, 1.2),
                  ambient=0.4)
    poses = orbit(p.num_views, (0.0, 0.0, 0.25), 2.0, 1.35, 0.25, phase_deg=rng.uniform(0, 360))
    return scene, poses


BUILDERS: Dict[str, Callable[[np.random.Generator, SynthPreset], Tuple[SynthScene, List[np.ndarray]]]] = {
    "demo": _demo,
    "forward": _forward,
    "orbit": _orbit,
}
