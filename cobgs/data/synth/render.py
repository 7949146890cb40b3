"""Vectorised ray caster of synthetic scenes: colour, and per-object subsample coverage.

Each pixel is sampled on a regular ``s x s`` grid of sub-pixel positions. For every
subsample the *first* surface hit decides both its colour (Lambertian shading under a
directional light, with a shadow ray for hard shadows) and which object it belongs to, so
coverage respects occlusion. Rays are processed in chunks of whole pixels to bound memory.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Tuple

import numpy as np

from cobgs.errors import InputError
from cobgs.data.synth.cameras import PinholeCamera
from cobgs.data.synth.primitives import T_MIN, Primitive, rowdot
from cobgs.data.synth.textures import Texture, _lattice, evaluate

RGB = Tuple[float, float, float]

# Shadow rays start this far (scene units) off the surface along the normal, far above
# float64 rounding at scene scale (~1e-15 x 10) and far below any feature size.
_SHADOW_OFFSET = 1e-5


@dataclass(frozen=True)
class SceneObject:
    """A textured primitive. ``id`` 0 marks background (ground, walls); objects have ids
    1..K, unique, and get masks; ``target`` says whether it is a segmentation target."""

    name: str
    id: int
    shape: Primitive
    texture: Texture
    target: bool = True

    def to_json(self) -> dict:
        return {"name": self.name, "id": self.id, "kind": self.shape.kind,
                "target": self.target, "params": self.shape.to_json(),
                "texture": self.texture.to_json()}


@dataclass(frozen=True)
class SynthScene:
    """Objects (ids 1..K), background surfaces (id 0) and lighting.

    Attributes:
        objects: the maskable objects, ids 1..K in order.
        background: ground, walls; never masked.
        light_dir: [3] direction *towards* the directional light (normalised on use).
        ambient: fraction of light that reaches every surface (shadowed ones too).
        sky: RGB of rays that hit nothing.
    """

    objects: Tuple[SceneObject, ...]
    background: Tuple[SceneObject, ...]
    light_dir: Tuple[float, float, float]
    ambient: float = 0.35
    sky: RGB = (0.75, 0.82, 0.9)

    def __post_init__(self) -> None:
        ids = [o.id for o in self.objects]
        if ids != list(range(1, len(ids) + 1)):
            raise InputError(f"scene object ids must be 1..K in order, got {ids}")
        names = [o.name for o in self.objects]
        if len(set(names)) != len(names) or any(not n or "/" in n for n in names):
            raise InputError(f"scene object names must be unique, non-empty, no '/': {names}")
        if any(b.id != 0 for b in self.background):
            raise InputError("background surfaces must have id 0")
        if not 0.0 <= self.ambient <= 1.0:
            raise InputError(f"ambient must be in [0, 1], got {self.ambient}")

    @property
    def surfaces(self) -> Tuple[SceneObject, ...]:
        return self.objects + self.background


@dataclass
class RenderedView:
    """One rendered view.

    Attributes:
        rgb: [H, W, 3] uint8 colour (mean over subsamples, rounded).
        hits: [K, H, W] uint16, per object, how many of the pixel's subsamples see it first.
        subsamples: subsamples per pixel (s * s).
    """

    rgb: np.ndarray
    hits: np.ndarray
    subsamples: int


class _Caster:
    """Holds the per-scene constants (bounds, texture lattices) for many casts."""

    def __init__(self, scene: SynthScene):
        self.scene = scene
        self.surfaces = scene.surfaces
        self.bounds = [s.shape.bound() for s in self.surfaces]
        self.tables: Dict[int, np.ndarray] = {}
        for s in self.surfaces:
            if s.texture.seed not in self.tables:
                self.tables[s.texture.seed] = _lattice(s.texture.seed)
        light = np.asarray(scene.light_dir, dtype=np.float64)
        self.light = light / np.linalg.norm(light)

    @staticmethod
    def _rows(a: np.ndarray, idx: np.ndarray) -> np.ndarray:
        return a if a.ndim == 1 else a[idx]

    def _candidates(self, i: int, o: np.ndarray, d: np.ndarray, t_best: np.ndarray) -> np.ndarray:
        """Indices of rays that may hit surface i before t_best (bounding-sphere cull).

        o and d are [N, 3] or a shared [3] (see :func:`rowdot`)."""
        bnd = self.bounds[i]
        if bnd is None:
            return np.arange(len(t_best))
        c, r = bnd
        oc = o - c
        b = rowdot(oc, d)
        cc = rowdot(oc, oc) - r * r
        disc = b * b - cc
        sq = np.sqrt(np.maximum(disc, 0.0))
        keep = (disc >= 0) & (-b + sq > T_MIN) & (-b - sq < t_best)
        return np.flatnonzero(keep)

    def first_hit(self, o: np.ndarray, d: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Nearest hit distance [N] (inf on a miss) and surface index [N] (-1 on a miss)
        of rays o + t d; o is a shared [3] eye or [N, 3], d is [N, 3]."""
        t_best = np.full(len(d), np.inf)
        which = np.full(len(d), -1, dtype=np.int64)
        for i, s in enumerate(self.surfaces):
            idx = self._candidates(i, o, d, t_best)
            if len(idx) == 0:
                continue
            t = s.shape.intersect(self._rows(o, idx), d[idx])
            closer = t < t_best[idx]
            sel = idx[closer]
            t_best[sel] = t[closer]
            which[sel] = i
        return t_best, which

    def silhouettes(self, o: np.ndarray, d: np.ndarray, k: int) -> np.ndarray:
        """[k, N] bool: does the ray o + t d hit object i at all (i < k), whatever lies
        in front of it — each object's whole (amodal) silhouette."""
        out = np.zeros((k, len(d)), dtype=bool)
        no_limit = np.full(len(d), np.inf)
        for i in range(k):
            idx = self._candidates(i, o, d, no_limit)
            if len(idx):
                out[i, idx] = np.isfinite(self.surfaces[i].shape.intersect(self._rows(o, idx), d[idx]))
        return out

    def occluded(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        """[N] bool: does anything lie along the shadow rays o [N, 3] + t d, t > 0, with a
        shared direction d [3] (directional light)."""
        blocked = np.zeros(len(o), dtype=bool)
        no_limit = np.full(len(o), np.inf)
        for i, s in enumerate(self.surfaces):
            open_idx = np.flatnonzero(~blocked)
            if len(open_idx) == 0:
                break
            oo = o[open_idx]
            sub = self._candidates(i, oo, d, no_limit[: len(open_idx)])
            if len(sub) == 0:
                continue
            t = s.shape.intersect(oo[sub], d)
            blocked[open_idx[sub[np.isfinite(t)]]] = True
        return blocked

    def shade(self, o: np.ndarray, d: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """RGB [N, 3] and surface index [N] (-1: sky) of rays o + t d [N, 3] from a
        shared eye o [3]."""
        t, which = self.first_hit(o, d)
        rgb = np.empty((len(d), 3))
        rgb[:] = np.asarray(self.scene.sky)
        hit = np.flatnonzero(which >= 0)
        p = o + t[hit, None] * d[hit]
        normal = np.empty((len(hit), 3))
        albedo = np.empty((len(hit), 3))
        w_hit = which[hit]
        for i, s in enumerate(self.surfaces):
            sel = np.flatnonzero(w_hit == i)
            if len(sel) == 0:
                continue
            n, q = s.shape.surface(p[sel])
            normal[sel] = n
            albedo[sel] = evaluate(s.texture, q, self.tables[s.texture.seed])
        # Two-sided planes (and grazing hits) must be lit from the side the viewer is on.
        flip = np.einsum("ij,ij->i", normal, d[hit]) > 0
        normal[flip] *= -1.0
        lambert = np.maximum(normal @ self.light, 0.0)
        lit = np.flatnonzero(lambert > 0)
        if len(lit):
            so = p[lit] + _SHADOW_OFFSET * normal[lit]
            lambert[lit[self.occluded(so, self.light)]] = 0.0
        amb = self.scene.ambient
        rgb[hit] = albedo * (amb + (1.0 - amb) * lambert)[:, None]
        return rgb, which


def subsample_offsets(s: int) -> np.ndarray:
    """[s*s, 2] sub-pixel (x, y) offsets in [0, 1): centres of an s x s grid."""
    g = (np.arange(s) + 0.5) / s
    xx, yy = np.meshgrid(g, g, indexing="xy")
    return np.stack([xx.ravel(), yy.ravel()], axis=1)


def render_view(scene: SynthScene, camera: PinholeCamera, supersampling: int,
                chunk_rays: int = 1 << 14, caster: "_Caster | None" = None) -> RenderedView:
    """Ray-cast one view.

    Args:
        scene: the scene.
        camera: intrinsics and camera->world pose (OpenCV axes).
        supersampling: s; each pixel is sampled on an s x s grid.
        chunk_rays: rays per chunk. Small enough that the temporaries stay in cache and
            reuse freed memory (65536 doubles the CPU time through page faults alone).
        caster: reuse the per-scene constants across views (built when None).
    Returns:
        The colour image and per-object first-hit counts.
    """
    caster = caster or _Caster(scene)
    w, h = camera.width, camera.height
    s2 = supersampling * supersampling
    npix = w * h
    rgb = np.empty((npix, 3))
    k = len(scene.objects)
    hits = np.zeros((k, npix), dtype=np.uint16)
    # Map surface index -> object channel (background and sky -> none).
    chan = np.full(len(caster.surfaces) + 1, -1, dtype=np.int64)
    chan[: k] = np.arange(k)
    for pix, eye, d in _ray_chunks(camera, supersampling, chunk_rays):
        col, which = caster.shade(eye, d)
        rgb[pix] = col.reshape(len(pix), s2, 3).mean(axis=1)
        # Count, per pixel, the subsamples of each object in one bincount; channel k
        # collects background and sky (which == -1 indexes the trailing entry of chan).
        ch = chan[which]
        ch[ch < 0] = k
        key = np.repeat(np.arange(len(pix)), s2) * (k + 1) + ch
        counts = np.bincount(key, minlength=len(pix) * (k + 1)).reshape(len(pix), k + 1)
        hits[:, pix] = counts[:, :k].T
    img = np.clip(np.rint(rgb * 255.0), 0, 255).astype(np.uint8).reshape(h, w, 3)
    return RenderedView(rgb=img, hits=hits.reshape(k, h, w), subsamples=s2)


def _ray_chunks(camera: PinholeCamera, supersampling: int, chunk_rays: int):
    """Yield (pixel indices [P], eye [3], unit ray directions [P * s * s, 3]) over the
    image in chunks of about ``chunk_rays`` rays, each pixel sampled on an s x s grid."""
    if not (isinstance(supersampling, int) and 1 <= supersampling <= 16):
        raise InputError(f"supersampling must be an int in [1, 16], got {supersampling!r}")
    w, h = camera.width, camera.height
    s2 = supersampling * supersampling
    offs = subsample_offsets(supersampling)
    c2w = camera.c2w_array
    rot, eye = c2w[:3, :3], c2w[:3, 3]
    npix = w * h
    px_chunk = max(1, chunk_rays // s2)
    for p0 in range(0, npix, px_chunk):
        pix = np.arange(p0, min(npix, p0 + px_chunk))
        u = ((pix % w)[:, None] + offs[None, :, 0]).ravel()
        v = ((pix // w)[:, None] + offs[None, :, 1]).ravel()
        dc = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy,
                       np.ones_like(u)], axis=1)
        d = dc @ rot.T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        yield pix, eye, d


def silhouette_hits(scene: SynthScene, camera: PinholeCamera, supersampling: int,
                    chunk_rays: int = 1 << 14, caster: "_Caster | None" = None) -> np.ndarray:
    """[K, H, W] uint16: per object, how many of the pixel's subsamples hit it at all,
    occluders ignored (its amodal silhouette; the mask rule of :func:`render_view`'s hits
    applies: a strict majority of subsamples)."""
    caster = caster or _Caster(scene)
    s2 = supersampling * supersampling
    k = len(scene.objects)
    out = np.zeros((k, camera.width * camera.height), dtype=np.uint16)
    for pix, eye, d in _ray_chunks(camera, supersampling, chunk_rays):
        sil = caster.silhouettes(eye, d, k)
        out[:, pix] = sil.reshape(k, len(pix), s2).sum(axis=2)
    return out.reshape(k, camera.height, camera.width)


def make_caster(scene: SynthScene) -> _Caster:
    """Per-scene constants to share between :func:`render_view` calls."""
    return _Caster(scene)

