"""Mask-noise emulation: the errors of SAM-style video masks, applied to exact masks.

COB-GS claims robustness against erroneous 2D masks (docs/method.md §2, RAEM). To test that
with exact synthetic masks we corrupt them the way tracked SAM masks go wrong, each kind of
error happening to a mask with its own probability:

- *dropped frame*: the tracker lost the object, the mask is empty (written as an all-zero
  mask, not as a missing file: a missing file means "no annotation");
- *erosion / dilation*: the boundary sits a few pixels inside / outside the object;
- *boundary jitter*: the boundary wobbles by up to a few pixels along its length (a smooth
  random displacement field warps the mask);
- *spurious blobs*: small discs of foreground away from the object.

The random stream of each mask is derived from the seed and a key (``"<object>/<stem>"``
for folders), so a mask's noise does not depend on which other masks are processed or in
which order.
"""

from __future__ import annotations

import dataclasses
import json
import os
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from cobgs._atomic import build_folder_atomic
from cobgs.configs import MaskNoiseParams  # noqa: F401 (defined there)
from cobgs.errors import DataError, InputError


@dataclass(frozen=True)
class NoiseRecord:
    """What was done to one mask.

    Attributes:
        dropped: replaced by an empty mask.
        morph_px: > 0 dilated by that radius, < 0 eroded by -morph_px, 0 untouched.
        jittered: boundary jittered.
        blobs: number of spurious blobs added.
    """

    dropped: bool = False
    morph_px: int = 0
    jittered: bool = False
    blobs: int = 0


def mask_rng(params: MaskNoiseParams, key: str | int) -> np.random.Generator:
    """The random stream of the mask named ``key`` (stable across runs and orders)."""
    k = zlib.crc32(str(key).encode("utf-8"))
    return np.random.default_rng([0x4D41534B, params.seed, k])


def _disc(radius: int) -> np.ndarray:
    import cv2

    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def _jitter(mask: np.ndarray, amplitude: float, scale: float, rng: np.random.Generator) -> np.ndarray:
    """Warp ``mask`` [H, W] uint8 by a smooth random field with peak ``amplitude`` px."""
    import cv2

    h, w = mask.shape
    fields = []
    for _ in range(2):
        f = cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), scale,
                             borderType=cv2.BORDER_REFLECT)
        peak = float(np.abs(f).max())
        fields.append(f * (amplitude / peak) if peak > 0 else f)
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    return cv2.remap(mask, gx + fields[0], gy + fields[1], interpolation=cv2.INTER_NEAREST,
                     borderMode=cv2.BORDER_REPLICATE)


def _blobs(mask: np.ndarray, count: int, params: MaskNoiseParams, rng: np.random.Generator) -> int:
    """Paint up to ``count`` discs centred on background pixels; returns how many."""
    import cv2

    bg_r, bg_c = np.nonzero(mask == 0)
    if len(bg_r) == 0:
        return 0
    for _ in range(count):
        i = int(rng.integers(len(bg_r)))
        r = int(rng.integers(params.blob_radius_min_px, params.blob_radius_max_px + 1))
        cv2.circle(mask, (int(bg_c[i]), int(bg_r[i])), r, 255, thickness=-1)
    return count


def apply_mask_noise(mask: np.ndarray, params: MaskNoiseParams, rng: np.random.Generator
                     ) -> Tuple[np.ndarray, NoiseRecord]:
    """Corrupt one mask.

    Args:
        mask: [H, W] bool or uint8 (non-zero = object).
        params: rates and strengths.
        rng: the mask's random stream (see :func:`mask_rng`).
    Returns:
        The noisy mask [H, W] uint8 in {0, 255} and what was done.
    """
    import cv2

    m = np.asarray(mask)
    if m.ndim != 2 or m.dtype not in (np.bool_, np.uint8):
        raise InputError(f"mask must be a [H, W] bool or uint8 array, got {m.dtype} {list(m.shape)}")
    out = np.where(m > 0, 255, 0).astype(np.uint8)
    # Every draw happens whatever the outcome, so one decision never shifts the random
    # numbers of the others (a mask's jitter does not change when its drop rate does).
    u = rng.random(5)
    morph_r = int(rng.integers(1, params.morph_max_px + 1))
    n_blobs = int(rng.integers(1, params.blob_count_max + 1))
    sub = np.random.default_rng(rng.integers(2**63))
    if u[0] < params.drop_rate:
        return np.zeros_like(out), NoiseRecord(dropped=True)
    morph = 0
    if u[1] < params.morph_rate:
        if u[2] < params.dilate_fraction:
            out = cv2.dilate(out, _disc(morph_r))
            morph = morph_r
        else:
            out = cv2.erode(out, _disc(morph_r), borderType=cv2.BORDER_REPLICATE)
            morph = -morph_r
    jittered = bool(u[3] < params.jitter_rate)
    if jittered:
        out = _jitter(out, params.jitter_amplitude_px, params.jitter_scale_px, sub)
    blobs = _blobs(out, n_blobs, params, sub) if u[4] < params.blob_rate else 0
    return out, NoiseRecord(dropped=False, morph_px=morph, jittered=jittered, blobs=blobs)


def noise_masks(masks: Sequence[np.ndarray], params: MaskNoiseParams,
                keys: Optional[Sequence[str | int]] = None
                ) -> Tuple[List[np.ndarray], List[NoiseRecord]]:
    """Corrupt a sequence of masks [H, W]; mask i uses the stream of ``keys[i]`` (default i)."""
    keys = list(range(len(masks))) if keys is None else list(keys)
    if len(keys) != len(masks):
        raise InputError(f"got {len(masks)} masks but {len(keys)} keys")
    outs, recs = [], []
    for m, k in zip(masks, keys):
        o, r = apply_mask_noise(m, params, mask_rng(params, k))
        outs.append(o)
        recs.append(r)
    return outs, recs


def noise_mask_folder(src: os.PathLike | str, dst: os.PathLike | str, params: MaskNoiseParams,
                      *, overwrite: bool = False, progress: bool = True) -> Dict[str, Dict[str, dict]]:
    """Write a noisy copy of a masks folder (``<src>/<object>/<stem>.png``, 0/255 PNG).

    ``dst`` gets the same layout plus ``noise.json`` (the params and, per object and stem,
    the :class:`NoiseRecord`). Written to a temporary sibling and renamed into place.

    Returns:
        {object: {stem: record as a dict}}.
    """
    import cv2
    from tqdm import tqdm

    src, dst = Path(src), Path(dst)
    if not src.is_dir():
        raise InputError(f"mask folder {src} does not exist")
    objects = sorted(p.name for p in src.iterdir() if p.is_dir())
    if not objects:
        raise DataError("no object sub-folders (<masks>/<object>/<stem>.png) found", src)
    if dst.exists() and (not dst.is_dir() or any(dst.iterdir())):
        if not overwrite:
            raise InputError(f"output mask folder {dst} exists and is not empty (use overwrite)")
        if dst.is_symlink() or not dst.is_dir() or not (dst / "noise.json").is_file():
            raise InputError(f"overwrite replaces only a mask folder `cobgs synth-noise` wrote (with its "
                             f"noise.json); {dst} is not one: refusing to delete it (choose another output)")
        if dst.resolve() == src.resolve() or src.resolve().is_relative_to(dst.resolve()):
            raise InputError(f"output mask folder {dst} holds the input {src}: refusing to replace it")
    files = [(o, f) for o in objects for f in sorted((src / o).glob("*.png"))]
    log: Dict[str, Dict[str, dict]] = {o: {} for o in objects}

    def build(tmp: Path) -> None:
        for o in objects:
            (tmp / o).mkdir()
        for o, f in tqdm(files, desc="mask noise", unit="mask", disable=not progress):
            m = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
            if m is None or m.ndim != 2:
                raise DataError("expected an 8-bit single-channel mask PNG", f)
            noisy, rec = apply_mask_noise(m, params, mask_rng(params, f"{o}/{f.stem}"))
            if not cv2.imwrite(str(tmp / o / f.name), noisy):
                raise DataError("could not write PNG", tmp / o / f.name)
            log[o][f.stem] = dataclasses.asdict(rec)
        with open(tmp / "noise.json", "w", encoding="utf-8") as fh:
            json.dump({"params": dataclasses.asdict(params), "source": str(src), "masks": log},
                      fh, indent=1)

    build_folder_atomic(dst, build)
    return log
