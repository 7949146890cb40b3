"""Analytic primitives for the synthetic scene ray caster.

World frame: right-handed, +z up, the ground is z = 0. Each primitive answers three
vectorised questions for a batch of rays / points:

- ``intersect(o, d)``: distance ``t > T_MIN`` to the nearest hit along each ray (inf on a
  miss), for rays ``o + t d``;
- ``surface(p)``: outward unit normal and texture coordinate at hit points ``p``;
- ``bound()``: a bounding sphere used to cull rays cheaply (None for unbounded planes).

Texture coordinates are the point in the primitive's local frame, except that on flat faces
the coordinate along the face normal is NaN, which the texture replaces by a mid-cell
constant: a solid texture sampled exactly on a cell boundary (a face at local z = 0.5 with
checker cells of 0.5) would otherwise flicker with rounding.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np

from cobgs.errors import InputError

Vec3 = Tuple[float, float, float]
Mat3 = Tuple[Vec3, Vec3, Vec3]

# Hits closer than this (scene units) are ignored: it keeps shadow rays, which start
# 1e-4 off the surface, from re-hitting their own surface through rounding.
T_MIN = 1e-6


def _unit(v, name: str) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    n = float(np.linalg.norm(a))
    if a.shape != (3,) or not n > 0:
        raise InputError(f"{name} must be a non-zero 3-vector, got {v!r}")
    return a / n


def _positive(x: float, name: str) -> None:
    if not (isinstance(x, (int, float)) and x > 0 and math.isfinite(x)):
        raise InputError(f"{name} must be a finite number > 0, got {x!r}")


def frame_from_axis(axis) -> np.ndarray:
    """[3, 3] rotation (columns = local x, y, z in world) whose local z is ``axis``."""
    z = _unit(axis, "axis")
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


def rotation_from_euler_deg(yaw: float, pitch: float = 0.0, roll: float = 0.0) -> Mat3:
    """Local->world rotation R = Rz(yaw) Ry(pitch) Rx(roll), angles in degrees."""
    a, b, c = (math.radians(v) for v in (yaw, pitch, roll))
    rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    rx = np.array([[1, 0, 0], [0, math.cos(c), -math.sin(c)], [0, math.sin(c), math.cos(c)]])
    r = rz @ ry @ rx
    return tuple(tuple(float(v) for v in row) for row in r)  # type: ignore[return-value]


def rowdot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot product of [N, 3] / [3] arrays (either may be a single shared [3]
    vector: primary rays share their origin, shadow rays their direction)."""
    if a.ndim == 1:
        return b @ a
    if b.ndim == 1:
        return a @ b
    return np.einsum("ij,ij->i", a, b)


def _nearest_positive(*ts: np.ndarray) -> np.ndarray:
    ts = np.broadcast_arrays(*ts)
    out = np.full(ts[0].shape, np.inf)
    for t in ts:
        ok = (t > T_MIN) & (t < out)
        out = np.where(ok, t, out)
    return out


@dataclass(frozen=True)
class Sphere:
    """Sphere of ``radius`` around ``center`` (scene units)."""

    center: Vec3
    radius: float
    kind = "sphere"

    def __post_init__(self) -> None:
        _positive(self.radius, "sphere radius")

    def bound(self) -> Optional[Tuple[np.ndarray, float]]:
        return np.asarray(self.center, dtype=np.float64), float(self.radius)

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        """[N] nearest hit distance of rays o + t d (d unit), inf on a miss. o and d are
        [N, 3], or one of them a shared [3] (as for every ``intersect``)."""
        oc = o - np.asarray(self.center)
        b = rowdot(oc, d)
        c = rowdot(oc, oc) - self.radius**2
        disc = b * b - c
        hit = disc >= 0
        sq = np.sqrt(np.where(hit, disc, 0.0))
        t = _nearest_positive(-b - sq, -b + sq)
        return np.where(hit, t, np.inf)

    def surface(self, p: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Outward normals [N, 3] and texture coordinates [N, 3] at surface points p [N, 3]."""
        q = p - np.asarray(self.center)
        return q / self.radius, q

    def to_json(self) -> dict:
        return {"center": list(self.center), "radius": self.radius}


@dataclass(frozen=True)
class Box:
    """Oriented box: ``center``, ``half_extents`` along its local axes, ``rotation``
    (local->world, row-major 3x3, columns are the local axes in world coordinates)."""

    center: Vec3
    half_extents: Vec3
    rotation: Mat3 = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    kind = "box"

    def __post_init__(self) -> None:
        for k, h in enumerate(self.half_extents):
            _positive(h, f"box half_extents[{k}]")
        r = np.asarray(self.rotation, dtype=np.float64)
        if r.shape != (3, 3) or not np.allclose(r @ r.T, np.eye(3), atol=1e-9) or np.linalg.det(r) < 0:
            raise InputError(f"box rotation must be a proper 3x3 rotation, got {self.rotation!r}")

    def bound(self) -> Optional[Tuple[np.ndarray, float]]:
        return np.asarray(self.center, dtype=np.float64), float(np.linalg.norm(self.half_extents))

    def _local(self, p: np.ndarray) -> np.ndarray:
        return (p - np.asarray(self.center)) @ np.asarray(self.rotation)

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        """[N] nearest hit distance (slab test in the local frame), inf on a miss."""
        r = np.asarray(self.rotation)
        ol = (o - np.asarray(self.center)) @ r
        dl = d @ r
        h = np.asarray(self.half_extents)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / dl
            t1 = (-h - ol) * inv  # [N, 3] whichever of o, d is shared
            t2 = (h - ol) * inv
        # A ray parallel to a slab gives +-inf, or nan when it lies in a face plane;
        # fmin/fmax skip the nan so such a slab does not constrain the interval.
        tnear = np.fmax.reduce(np.fmin(t1, t2), axis=1)
        tfar = np.fmin.reduce(np.fmax(t1, t2), axis=1)
        hit = (tfar >= tnear) & (tfar > T_MIN)
        t = np.where(tnear > T_MIN, tnear, tfar)
        return np.where(hit, t, np.inf)

    def surface(self, p: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Outward normals [N, 3] and texture coordinates [N, 3] at surface points p [N, 3]."""
        q = self._local(p)
        h = np.asarray(self.half_extents)
        # The hit face is the one the point is closest to.
        face = np.argmin(h[None, :] - np.abs(q), axis=1)
        sign = np.sign(q[np.arange(len(q)), face])
        sign[sign == 0] = 1.0
        nl = np.zeros_like(q)
        nl[np.arange(len(q)), face] = sign
        tex = q.copy()
        tex[np.arange(len(q)), face] = np.nan
        return nl @ np.asarray(self.rotation).T, tex

    def lowest_z(self) -> float:
        """World z of the lowest corner (to rest a rotated box on the ground)."""
        r = np.asarray(self.rotation)
        h = np.asarray(self.half_extents)
        return float(self.center[2] - np.abs(r[2]) @ h)

    def to_json(self) -> dict:
        return {"center": list(self.center), "half_extents": list(self.half_extents),
                "rotation": [list(r) for r in self.rotation]}


@dataclass(frozen=True)
class Cylinder:
    """Capped cylinder: disc of ``radius`` at ``base``, extruded ``height`` along ``axis``."""

    base: Vec3
    axis: Vec3
    radius: float
    height: float
    kind = "cylinder"

    def __post_init__(self) -> None:
        _unit(self.axis, "cylinder axis")
        _positive(self.radius, "cylinder radius")
        _positive(self.height, "cylinder height")

    def _frame(self) -> np.ndarray:
        return frame_from_axis(self.axis)

    def bound(self) -> Optional[Tuple[np.ndarray, float]]:
        a = _unit(self.axis, "axis")
        c = np.asarray(self.base) + 0.5 * self.height * a
        return c, float(math.hypot(0.5 * self.height, self.radius))

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        """[N] nearest hit distance (side, bottom cap, top cap), inf on a miss."""
        r = self._frame()
        ol = (o - np.asarray(self.base)) @ r
        dl = d @ r
        ox, oy, oz = ol[..., 0], ol[..., 1], ol[..., 2]
        dx, dy, dz = dl[..., 0], dl[..., 1], dl[..., 2]
        a = dx * dx + dy * dy
        b = ox * dx + oy * dy
        c = ox * ox + oy * oy - self.radius**2
        disc = b * b - a * c
        ok = (disc >= 0) & (a > 1e-18)
        sq = np.sqrt(np.where(ok, disc, 0.0))
        a_safe = np.where(ok, a, 1.0)
        ts = []
        for sgn in (-1.0, 1.0):
            t = (-b + sgn * sq) / a_safe
            z = oz + t * dz
            ts.append(np.where(ok & (z >= 0) & (z <= self.height), t, np.inf))
        with np.errstate(divide="ignore", invalid="ignore"):
            for zc in (0.0, self.height):
                t = (zc - oz) / dz
                x = ox + t * dx
                y = oy + t * dy
                ts.append(np.where(np.isfinite(t) & (x * x + y * y <= self.radius**2), t, np.inf))
        return _nearest_positive(*ts)

    def surface(self, p: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Outward normals [N, 3] and texture coordinates [N, 3] at surface points p [N, 3]."""
        r = self._frame()
        q = (p - np.asarray(self.base)) @ r
        rho = np.hypot(q[:, 0], q[:, 1])
        d_side = np.abs(self.radius - rho)
        d_bot = np.abs(q[:, 2])
        d_top = np.abs(self.height - q[:, 2])
        nl = np.zeros_like(q)
        side = (d_side <= d_bot) & (d_side <= d_top)
        nl[side, 0] = q[side, 0] / np.maximum(rho[side], 1e-12)
        nl[side, 1] = q[side, 1] / np.maximum(rho[side], 1e-12)
        top = ~side & (d_top < d_bot)
        bot = ~side & ~top
        nl[top, 2] = 1.0
        nl[bot, 2] = -1.0
        tex = q.copy()
        tex[top | bot, 2] = np.nan
        return nl @ r.T, tex

    def to_json(self) -> dict:
        return {"base": list(self.base), "axis": list(self.axis), "radius": self.radius,
                "height": self.height}


@dataclass(frozen=True)
class Plane:
    """Infinite two-sided plane through ``point`` with unit ``normal``; ``tangent`` fixes
    the texture's in-plane orientation."""

    point: Vec3
    normal: Vec3
    tangent: Vec3
    kind = "plane"

    def __post_init__(self) -> None:
        n = _unit(self.normal, "plane normal")
        t = _unit(self.tangent, "plane tangent")
        if abs(float(n @ t)) > 1e-6:
            raise InputError(f"plane tangent {self.tangent} must be orthogonal to normal {self.normal}")

    def bound(self) -> Optional[Tuple[np.ndarray, float]]:
        return None

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        """[N] hit distance, inf for rays parallel to or pointing away from the plane."""
        n = _unit(self.normal, "normal")
        den = d @ n
        num = (np.asarray(self.point) - o) @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.atleast_1d(num / den)
        return np.where(np.isfinite(t) & (t > T_MIN), t, np.inf)

    def surface(self, p: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Normals [N, 3] (the plane normal; the renderer flips it towards the viewer) and
        texture coordinates [N, 3] (in-plane coordinates, NaN third coordinate)."""
        n = _unit(self.normal, "normal")
        u = _unit(self.tangent, "tangent")
        v = np.cross(n, u)
        q = p - np.asarray(self.point)
        tex = np.stack([q @ u, q @ v, np.full(len(p), np.nan)], axis=1)
        return np.broadcast_to(n, p.shape).copy(), tex

    def to_json(self) -> dict:
        return {"point": list(self.point), "normal": list(self.normal),
                "tangent": list(self.tangent)}


Primitive = Sphere | Box | Cylinder | Plane
