"""Pinhole cameras and capture trajectories of the synthetic scene generator.

Poses are camera->world 4x4 matrices in **OpenCV axes** (+x right, +y down, +z forward)
inside the generator; :func:`opencv_to_opengl` gives the OpenGL / NeRF axes that
``transforms.json`` stores. Pixel ``(col, row)`` covers ``[col, col+1) x [row, row+1)``, so
its centre is at ``(col + 0.5, row + 0.5)`` and ``cx = width / 2`` is the image centre
(the COLMAP convention).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Tuple

import numpy as np

from cobgs.errors import InputError

# transforms.json flips the camera's y and z axes (OpenGL looks down -z with +y up).
_CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class PinholeCamera:
    """Pixel intrinsics plus a camera->world pose in OpenCV axes.

    Attributes:
        width, height: image size in pixels.
        fx, fy, cx, cy: focal lengths and principal point in pixels.
        c2w: [4][4] camera->world matrix, OpenCV axes, row-major nested tuples.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    c2w: Tuple[Tuple[float, ...], ...]

    @property
    def c2w_array(self) -> np.ndarray:
        """[4, 4] float64 camera->world (OpenCV axes)."""
        return np.asarray(self.c2w, dtype=np.float64)

    @property
    def center(self) -> np.ndarray:
        """[3] camera centre in world coordinates."""
        return self.c2w_array[:3, 3]

    def project(self, points: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates [N, 2] (continuous, pixel centres at +0.5) and depths [N] of
        world points [N, 3]."""
        w2c = np.linalg.inv(self.c2w_array)
        pc = points @ w2c[:3, :3].T + w2c[:3, 3]
        z = pc[:, 2]
        uv = np.stack([self.fx * pc[:, 0] / z + self.cx, self.fy * pc[:, 1] / z + self.cy], 1)
        return uv, z


def intrinsics_from_fov(width: int, height: int, hfov_deg: float) -> Tuple[float, float, float, float]:
    """(fx, fy, cx, cy) of a square-pixel camera with horizontal field of view ``hfov_deg``."""
    if not 1.0 < hfov_deg < 170.0:
        raise InputError(f"horizontal field of view must be in (1, 170) degrees, got {hfov_deg}")
    f = 0.5 * width / math.tan(math.radians(hfov_deg) / 2)
    return f, f, width / 2.0, height / 2.0


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """[4, 4] camera->world (OpenCV axes) of a camera at ``eye`` looking at ``target``."""
    eye = np.asarray(eye, dtype=np.float64)
    fwd = np.asarray(target, dtype=np.float64) - eye
    if np.linalg.norm(fwd) == 0:
        raise InputError(f"camera eye {eye.tolist()} coincides with its target")
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(right) < 1e-9:
        raise InputError(f"camera looks along the up vector {up}; choose another target")
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, down, fwd, eye
    return m


def opencv_to_opengl(c2w: np.ndarray) -> np.ndarray:
    """[4, 4] camera->world with the camera's y and z axes flipped (OpenCV <-> OpenGL)."""
    return np.asarray(c2w, dtype=np.float64) @ _CV_TO_GL


def forward_facing(num_views: int, eye_center, target, spread_x: float, spread_z: float,
                   rng: np.random.Generator, jitter: float = 0.15) -> List[np.ndarray]:
    """LLFF-like hand-held capture: eyes on a jittered grid in the plane facing ``target``.

    The grid is walked row by row in serpentine order, so consecutive views are
    neighbours (what sequential matching expects of an ordered capture).

    Args:
        num_views: number of views (grid of about 4:3 columns:rows, truncated).
        eye_center: [3] centre of the grid of eyes.
        target: [3] point every camera looks at.
        spread_x, spread_z: half-width of the grid horizontally / vertically (scene units).
        rng: seeded generator for the jitter.
        jitter: eye jitter as a fraction of the grid step.
    Returns:
        ``num_views`` [4, 4] camera->world matrices (OpenCV axes).
    """
    if num_views < 2:
        raise InputError(f"a forward-facing capture needs >= 2 views, got {num_views}")
    cols = max(2, int(math.ceil(math.sqrt(num_views * 4 / 3))))
    rows = int(math.ceil(num_views / cols))
    eye_center = np.asarray(eye_center, dtype=np.float64)
    view_dir = np.asarray(target, dtype=np.float64) - eye_center
    right = np.cross(view_dir, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, view_dir)
    up /= np.linalg.norm(up)
    poses = []
    for r in range(rows):
        order = range(cols) if r % 2 == 0 else range(cols - 1, -1, -1)
        for c in order:
            if len(poses) == num_views:
                break
            gx = -1 + 2 * c / (cols - 1)
            gz = 1 - 2 * r / max(rows - 1, 1)
            jx, jz = rng.uniform(-jitter, jitter, 2)
            eye = eye_center + right * spread_x * (gx + jx * 2 / (cols - 1)) \
                + up * spread_z * (gz + jz * 2 / max(rows - 1, 1))
            poses.append(look_at(eye, target))
    return poses


def orbit(num_views: int, target, radius: float, height: float, height_wobble: float,
          phase_deg: float = 0.0) -> List[np.ndarray]:
    """360 degree capture: eyes on a circle around the vertical axis through ``target``.

    Args:
        num_views: views, evenly spaced in azimuth.
        target: [3] point every camera looks at (its x, y centre the circle).
        radius: circle radius (scene units).
        height: mean eye height (world z).
        height_wobble: eye height varies by +- this (two periods per turn), which gives the
            views a vertical baseline.
        phase_deg: azimuth of the first view.
    Returns:
        ``num_views`` [4, 4] camera->world matrices (OpenCV axes).
    """
    if num_views < 3:
        raise InputError(f"an orbit needs >= 3 views, got {num_views}")
    target = np.asarray(target, dtype=np.float64)
    poses = []
    for i in range(num_views):
        a = math.radians(phase_deg) + 2 * math.pi * i / num_views
        eye = [target[0] + radius * math.cos(a), target[1] + radius * math.sin(a),
               height + height_wobble * math.sin(2 * a)]
        poses.append(look_at(eye, target))
    return poses
