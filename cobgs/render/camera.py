"""Pinhole camera model shared by every reader, the trainer and the refinement.

Conventions (docs/data_formats.md): pixel intrinsics ``K`` [3, 3] where pixel centres sit
at integer + 0.5 coordinates of the continuous image plane (as in COLMAP), and a
world→camera matrix ``viewmat`` [4, 4] in **OpenCV axes** (+x right, +y down, +z forward).
Readers convert whatever the source uses (OpenGL/NeRF, LLFF "down-right-back") into this;
nothing downstream knows the source convention.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch
from torch import Tensor

from cobgs.errors import InputError, check_shape

# OpenGL / NeRF camera axes (+y up, +z backward) → OpenCV (+y down, +z forward): flip y, z.
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class Camera:
    """One pinhole camera.

    Attributes:
        K: [3, 3] float32 pixel intrinsics (fx, fy on the diagonal, cx, cy in column 2).
        viewmat: [4, 4] float32 world→camera transform, OpenCV axes.
        width: image width in pixels.
        height: image height in pixels.
        name: image file stem (used to match masks and held-out lists).
    """

    K: Tensor
    viewmat: Tensor
    width: int
    height: int
    name: str = ""

    def __post_init__(self):
        check_shape("Camera.K", self.K, (3, 3))
        check_shape("Camera.viewmat", self.viewmat, (4, 4))
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise InputError(
                f"Camera {self.name!r}: width and height must be positive, got "
                f"{self.width}x{self.height}"
            )

    # -- construction -------------------------------------------------------------------
    @staticmethod
    def from_c2w(
        c2w,  # [4, 4] or [3, 4] camera→world
        fx: float,
        fy: float,
        cx: float,
        cy: float,
        width: int,
        height: int,
        name: str = "",
        opengl: bool = False,
    ) -> "Camera":
        """Build a camera from a camera→world pose.

        Args:
            c2w: [4, 4] or [3, 4] camera→world matrix (numpy or tensor).
            fx, fy, cx, cy: pixel intrinsics.
            width, height: image size in pixels.
            name: image stem.
            opengl: True when ``c2w`` uses OpenGL/NeRF axes (+y up, +z backward).
        """
        m = np.asarray(c2w.detach().cpu() if isinstance(c2w, Tensor) else c2w, np.float64)
        if m.shape == (3, 4):
            m = np.concatenate([m, [[0.0, 0.0, 0.0, 1.0]]], 0)
        if m.shape != (4, 4):
            raise InputError(f"c2w must have shape [4, 4] or [3, 4], got {list(m.shape)}")
        if opengl:
            m = m @ _GL_TO_CV
        w2c = np.linalg.inv(m)
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        return Camera(
            K=torch.tensor(K, dtype=torch.float32),
            viewmat=torch.tensor(w2c, dtype=torch.float32),
            width=int(width),
            height=int(height),
            name=name,
        )

    # -- derived quantities -------------------------------------------------------------
    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def fov_x_rad(self) -> float:
        return 2.0 * math.atan(self.width / (2.0 * self.fx))

    @property
    def fov_y_rad(self) -> float:
        return 2.0 * math.atan(self.height / (2.0 * self.fy))

    @property
    def c2w(self) -> Tensor:
        """[4, 4] camera→world (OpenCV axes)."""
        return torch.linalg.inv(self.viewmat.double()).float()

    @property
    def center(self) -> Tensor:
        """[3] camera centre in world coordinates."""
        return self.c2w[:3, 3]

    # -- transforms ---------------------------------------------------------------------
    def scaled(self, factor: float) -> "Camera":
        """The same camera for an image resized by ``1 / factor`` (factor 2 halves it).

        The new size is ``round(size / factor)``; intrinsics scale by the actual size ratio
        per axis so that a resized image and its camera stay consistent.
        """
        if factor <= 0:
            raise InputError(f"scale factor must be > 0, got {factor}")
        w = max(1, int(round(self.width / factor)))
        h = max(1, int(round(self.height / factor)))
        return self.resized(w, h)

    def resized(self, width: int, height: int) -> "Camera":
        """The same camera for the image resized to ``width`` x ``height`` pixels."""
        sx, sy = width / self.width, height / self.height
        # Pixel centres are at +0.5, so the continuous image plane scales uniformly.
        S = torch.tensor([[sx, 0.0, 0.0], [0.0, sy, 0.0], [0.0, 0.0, 1.0]], dtype=self.K.dtype, device=self.K.device)
        return replace(self, K=S @ self.K, width=int(width), height=int(height))

    def cropped(self, x0: int, y0: int, width: int, height: int) -> "Camera":
        """The same camera for the ``width`` x ``height`` window of its image whose top-left
        pixel is ``(x0, y0)``: the principal point moves, the focal lengths stay."""
        if not (0 <= x0 and 0 <= y0 and 0 < width and 0 < height
                and x0 + width <= self.width and y0 + height <= self.height):
            raise InputError(f"Camera {self.name!r}: crop ({x0}, {y0}) {width}x{height} is outside "
                             f"its {self.width}x{self.height} image")
        K = self.K.clone()
        K[0, 2] -= x0
        K[1, 2] -= y0
        return replace(self, K=K, width=int(width), height=int(height))

    def to(self, device) -> "Camera":
        return replace(self, K=self.K.to(device), viewmat=self.viewmat.to(device))

    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Project world points to pixels.

        Args:
            points: [P, 3] world coordinates.

        Returns:
            (uv [P, 2] pixel coordinates, depth [P] camera-space z).
        """
        check_shape("points", points, (None, 3))
        R = self.viewmat[:3, :3].to(points)
        t = self.viewmat[:3, 3].to(points)
        pc = points @ R.T + t
        z = pc[:, 2]
        uv = pc[:, :2] / z.clamp_min(1e-12)[:, None] * torch.stack(
            [self.K[0, 0], self.K[1, 1]]
        ).to(points) + torch.stack([self.K[0, 2], self.K[1, 2]]).to(points)
        return uv, z


def scene_extent(cameras: list[Camera]) -> float:
    """NeRF++ radius: 1.1 x the largest distance of a camera centre from their mean.

    This is the scale 3DGS multiplies its position learning rate and its densification
    size thresholds by. A single camera (or coincident centres) gives radius 1.1 x 1, so
    that the thresholds stay finite.
    """
    if not cameras:
        raise InputError("scene_extent needs at least one camera")
    centers = torch.stack([c.center.double() for c in cameras])
    dist = (centers - centers.mean(0)).norm(dim=1).max().item()
    if dist <= 0.0:
        dist = 1.0
    return 1.1 * dist
