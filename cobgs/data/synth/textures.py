"""Procedural solid textures for the synthetic scene generator.

Every texture is a function of a 3D *texture coordinate* (the hit point in the primitive's
local frame, see :mod:`cobgs.data.synth.primitives`), so textures move with their object
and need no UV unwrapping. Randomness comes from a per-texture lattice table drawn from the
texture's seed: the same seed gives bit-identical colours on every run.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Tuple

import numpy as np

from cobgs.errors import InputError

RGB = Tuple[float, float, float]
KINDS = ("checker", "stripes", "noise", "dots")

# Side of the periodic random lattice. 64 cells of the finest scale used by the presets
# (about 0.05 scene units) span 3 units; coarser textures repeat even later, so the
# period is never visible in a frame.
_LATTICE = 64


@dataclass(frozen=True)
class Texture:
    """A procedural texture.

    Attributes:
        kind: "checker", "stripes", "noise" (value-noise colour) or "dots".
        colors: palette, RGB in [0, 1]. checker/stripes alternate colors[0] and colors[1];
            noise blends colors[0] -> colors[1] (and colors[2], if given, by a second noise
            field); dots paint colors[1:] (cycled by a hash) on a colors[0] base.
        scale: checker cell / stripe period / noise feature size / dot spacing, in scene
            units.
        grain: amplitude of a multiplicative fine value-noise modulation in [0, 1); adds
            corners and blobs that feature detectors can lock onto.
        seed: lattice seed of the noise, grain and dot placement.
    """

    kind: str
    colors: Tuple[RGB, ...]
    scale: float
    grain: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise InputError(f"texture kind must be one of {KINDS}, got {self.kind!r}")
        need = 2
        if len(self.colors) < need or any(len(c) != 3 for c in self.colors):
            raise InputError(
                f"texture {self.kind!r} needs at least {need} RGB colours, got {self.colors!r}"
            )
        if not self.scale > 0:
            raise InputError(f"texture scale must be > 0 scene units, got {self.scale}")
        if not 0 <= self.grain < 1:
            raise InputError(f"texture grain must be in [0, 1), got {self.grain}")

    def to_json(self) -> dict:
        return {"kind": self.kind, "colors": [list(c) for c in self.colors],
                "scale": self.scale, "grain": self.grain, "seed": self.seed}


def _lattice(seed: int) -> np.ndarray:
    """[L**3] float64 uniform values of the periodic lattice for ``seed``."""
    return np.random.default_rng([0xC0B6, seed]).random(_LATTICE**3)


def _cell_index(ix: np.ndarray, iy: np.ndarray, iz: np.ndarray) -> np.ndarray:
    m = _LATTICE - 1
    return ((ix & m) * _LATTICE + (iy & m)) * _LATTICE + (iz & m)


def value_noise(p: np.ndarray, table: np.ndarray) -> np.ndarray:
    """Smooth value noise in [0, 1].

    Args:
        p: [N, 3] coordinates in lattice cells.
        table: lattice of :func:`_lattice`.
    Returns:
        [N] float64, C1-continuous (smoothstep interpolation of the 8 cell corners).
    """
    fl = np.floor(p)
    i = fl.astype(np.int64)
    f = p - fl
    f = f * f * (3.0 - 2.0 * f)
    m, n = _LATTICE - 1, _LATTICE
    # Flat lattice index = (x * L + y) * L + z, with each axis wrapped to the period;
    # the two candidate terms per axis are formed once and summed per corner.
    ax = (((i[:, 0] & m) * n * n), (((i[:, 0] + 1) & m) * n * n))
    ay = (((i[:, 1] & m) * n), (((i[:, 1] + 1) & m) * n))
    az = ((i[:, 2] & m), ((i[:, 2] + 1) & m))
    fx, fy, fz = f[:, 0], f[:, 1], f[:, 2]
    out = np.zeros(len(p))
    for dx in (0, 1):
        wx = fx if dx else 1.0 - fx
        for dy in (0, 1):
            wxy = wx * (fy if dy else 1.0 - fy)
            axy = ax[dx] + ay[dy]
            for dz in (0, 1):
                wz = fz if dz else 1.0 - fz
                out += wxy * wz * table[axy + az[dz]]
    return out


def fbm(p: np.ndarray, table: np.ndarray, octaves: int) -> np.ndarray:
    """[N] fractal sum of ``octaves`` value-noise layers (lacunarity 2, gain 0.5), in [0, 1]."""
    total = np.zeros(len(p))
    amp, norm = 1.0, 0.0
    for k in range(octaves):
        # Offsetting each octave decorrelates the layers that share one lattice.
        total += amp * value_noise(p * (2.0**k) + 17.31 * k, table)
        norm += amp
        amp *= 0.5
    return total / norm


def _mix(a: np.ndarray, b: np.ndarray, w: np.ndarray) -> np.ndarray:
    return a[None, :] * (1.0 - w[:, None]) + b[None, :] * w[:, None]


def evaluate(tex: Texture, q: np.ndarray, table: np.ndarray | None = None) -> np.ndarray:
    """Albedo of ``tex`` at texture coordinates ``q``.

    Args:
        tex: the texture.
        q: [N, 3] texture coordinates (scene units, primitive-local frame).
        table: the texture's lattice (pass it to avoid redrawing it per call).
    Returns:
        [N, 3] float64 RGB albedo in [0, 1].
    """
    if table is None:
        table = _lattice(tex.seed)
    cols = np.asarray(tex.colors, dtype=np.float64)
    s = q / tex.scale
    # NaN marks the coordinate along a flat face's normal (see synth.primitives); putting
    # it mid-cell keeps the planar slice away from cell boundaries, where checker parity
    # would flicker with rounding and dots would be cut to slivers.
    s = np.where(np.isnan(s), 0.5, s)
    if tex.kind == "checker":
        c = np.floor(s).astype(np.int64)
        parity = ((c[:, 0] + c[:, 1] + c[:, 2]) & 1).astype(np.float64)
        rgb = _mix(cols[0], cols[1], parity)
    elif tex.kind == "stripes":
        # Stripes run across the local z axis (latitude bands on spheres, rings on
        # cylinders); a slight tilt keeps them from aligning with box edges.
        phase = s[:, 2] + 0.35 * s[:, 0]
        rgb = _mix(cols[0], cols[1], (np.floor(phase).astype(np.int64) & 1).astype(np.float64))
    elif tex.kind == "noise":
        n = fbm(s, table, 3)
        # Stretch the fbm histogram (it concentrates around 0.5) to use the whole palette.
        w = np.clip((n - 0.5) * 2.2 + 0.5, 0.0, 1.0)
        rgb = _mix(cols[0], cols[1], w)
        if len(cols) > 2:
            n2 = value_noise(s * 0.5 + 41.7, table)
            rgb = _mix_rows(rgb, cols[2], np.clip((n2 - 0.55) * 4.0, 0.0, 1.0))
    else:  # dots
        c = np.floor(s)
        ci = c.astype(np.int64)
        # Jitter the dot centre inside its cell by a hash; the margin keeps every dot
        # inside its own cell so one cell lookup decides membership.
        jit = np.stack([table[_cell_index(ci[:, 0] + 11 * k, ci[:, 1], ci[:, 2])]
                        for k in range(3)], axis=1)
        centre = c + 0.3 + 0.4 * jit
        centre[:, 2] = c[:, 2] + 0.5  # dots are discs on flat faces, balls in solids
        r2 = np.sum((s - centre) ** 2, axis=1)
        radius = 0.16 + 0.12 * table[_cell_index(ci[:, 0], ci[:, 1] + 23, ci[:, 2])]
        inside = r2 < radius**2
        pick = (table[_cell_index(ci[:, 0], ci[:, 1], ci[:, 2] + 5)] * (len(cols) - 1)).astype(
            np.int64
        )
        dot_col = cols[1 + np.minimum(pick, len(cols) - 2)]
        rgb = np.where(inside[:, None], dot_col, cols[0][None, :])
    if tex.grain > 0:
        g = value_noise(s * 4.0 + 5.5, table)
        rgb = rgb * (1.0 - tex.grain + 2.0 * tex.grain * g)[:, None]
    return np.clip(rgb, 0.0, 1.0)


def _mix_rows(a: np.ndarray, b: np.ndarray, w: np.ndarray) -> np.ndarray:
    return a * (1.0 - w[:, None]) + b[None, :] * w[:, None]
