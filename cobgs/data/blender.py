"""Blender / NeRF-synthetic scenes: ``transforms_{train,test}.json`` + RGBA PNGs.

Poses are camera→world in OpenGL axes, intrinsics come from ``camera_angle_x`` only
(square pixels, principal point at the image centre). The alpha channel is the exact
object mask: alpha > 0.5 (after area downscaling) marks the object.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from cobgs.render.camera import Camera
from cobgs.errors import DataError
from cobgs.data.scene import (Scene, View, find_object_files, load_rgb, make_scene, read_image_array,
                    read_mask_array, resize_mask, target_size)

# 3DGS initialises NeRF-synthetic scenes with random points in this cube.
NERF_SYNTHETIC_BOUNDS = ([-1.3, -1.3, -1.3], [1.3, 1.3, 1.3])


def read_blender(
    path: os.PathLike | str,
    *,
    downscale: float = 1.0,
    background: Sequence[float] = (1.0, 1.0, 1.0),
    mask_name: str = "object",
    train_split: str = "train",
    test_split: Optional[str] = "test",
) -> Scene:
    """Read a NeRF-synthetic scene.

    Args:
        path: folder with ``transforms_<split>.json``.
        downscale: divide the image size by this (4 turns 800x800 into 200x200).
        background: RGB in [0, 1] the RGBA images are composited on (white is the usual
            protocol for NeRF-synthetic).
        mask_name: object name of the alpha mask in ``View.masks``.
        train_split: split file used for training.
        test_split: split file used for held-out views (None: no test views).

    Returns:
        Scene with ``init_bounds`` set to the 3DGS random-initialisation cube.
    """
    root = Path(path)
    train = _read_split(root, train_split, downscale, background, mask_name)
    test = _read_split(root, test_split, downscale, background, mask_name) if test_split else []
    # The published NeRF-synthetic splits reuse names (train/r_0 and test/r_0 are different
    # images): a held-out view must never share a name with a training view, or it would be
    # trained on and scored; such test views are named "<split>_<stem>".
    taken = {v.name for v in train}
    for v in test:
        if v.name in taken:
            v.name = f"{test_split}_{v.name}"
            v.camera = dataclasses.replace(v.camera, name=v.name)
    scene = make_scene(
        train,
        test_every=0,
        source=root,
        kind="blender",
        init_bounds=NERF_SYNTHETIC_BOUNDS,
        background=tuple(float(b) for b in background),
    )
    scene.test = test
    scene.object_names = sorted({k for v in train + test for k in v.masks})
    return scene


def _read_split(root: Path, split: str, downscale, background, mask_name) -> list[View]:
    jf = root / f"transforms_{split}.json"
    meta = _load_json(jf)
    if "camera_angle_x" not in meta:
        raise DataError("missing 'camera_angle_x' (horizontal field of view in radians)", jf)
    if not isinstance(meta.get("frames"), list) or not meta["frames"]:
        raise DataError("missing or empty 'frames' list", jf)
    fov_x = meta["camera_angle_x"]
    if isinstance(fov_x, bool) or not isinstance(fov_x, (int, float)) or not 0 < fov_x < math.pi:
        raise DataError(f"'camera_angle_x' is {fov_x!r}, expected a number in (0, pi) (the "
                        "horizontal field of view in radians)", jf)
    views = []
    native = None
    for i, frame in enumerate(meta["frames"]):
        if "file_path" not in frame or "transform_matrix" not in frame:
            raise DataError(f"frame {i} lacks 'file_path' or 'transform_matrix'", jf)
        img_path = resolve_image(root, frame["file_path"])
        if native is None:  # NeRF-synthetic frames share one size; decode once to learn it
            a = read_image_array(img_path)
            native = (a.shape[1], a.shape[0])
        size = target_size(*native, downscale)
        image, alpha = load_rgb(img_path, size, background)
        if image.shape[1] != size[0] or image.shape[0] != size[1]:
            raise DataError("image size differs from the first frame's", img_path)
        w, h = size
        focal = 0.5 * w / math.tan(0.5 * fov_x)
        c2w = check_pose(frame["transform_matrix"], f"frame {i} ({frame['file_path']})", jf)
        cam = Camera.from_c2w(c2w, focal, focal, w / 2.0, h / 2.0, w, h, img_path.stem, opengl=True)
        masks, coverage = {}, {}
        if alpha is not None:
            masks[mask_name] = alpha > 0.5
            coverage[mask_name] = alpha
        # masks/<object>/<stem>.png beside the split files (the NeRF-synthetic layout plus
        # masks, e.g. for images without alpha or for several objects)
        for obj, f in find_object_files(root, img_path.stem, "masks").items():
            masks[obj] = resize_mask(read_mask_array(f, [native, size]), size)[0]
        views.append(View(cam, image, img_path.stem, masks, coverage, os.fspath(img_path)))
    return views


def check_pose(value, where: str, jf: Path) -> np.ndarray:
    """A camera-to-world matrix checked for what breaks a camera later: numbers only, 4x4
    (or 3x4), finite, a rotation block that is a rotation (orthonormal, det +1: a scaled or
    mirrored block would distort every projection) and [0, 0, 0, 1] as the last row."""
    try:
        c2w = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        raise DataError(f"{where}: transform_matrix must be a 4x4 list of numbers, got {value!r}"[:300],
                        jf) from None
    if c2w.shape not in ((4, 4), (3, 4)):
        raise DataError(f"{where}: transform_matrix must be 4x4, got {list(c2w.shape)}", jf)
    if not np.isfinite(c2w).all():
        raise DataError(f"{where}: transform_matrix has non-finite values", jf)
    if c2w.shape == (4, 4) and not np.allclose(c2w[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        raise DataError(f"{where}: transform_matrix's last row is {c2w[3].tolist()}, expected "
                        "[0, 0, 0, 1]", jf)
    r = c2w[:3, :3]
    err = float(np.abs(r.T @ r - np.eye(3)).max())
    if err > 1e-3 or np.linalg.det(r) < 0:
        raise DataError(f"{where}: transform_matrix's 3x3 block is not a rotation (|R^T R - I| = "
                        f"{err:.3g}, det {np.linalg.det(r):.4g}): a scaled, sheared or mirrored pose "
                        "is not a camera", jf)
    return c2w


def resolve_image(root: Path, file_path: str) -> Path:
    """The image a transforms file's ``file_path`` names; as the NeRF readers do, a path
    without an extension (``./train/r_0``) is looked up as .png, then .jpg / .jpeg."""
    p = root / file_path
    if p.suffix.lower() in (".png", ".jpg", ".jpeg") or p.is_file():
        if not p.is_file():
            raise DataError("image listed in the transforms file not found", p)
        return p
    for ext in (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG"):
        q = p.with_name(p.name + ext)
        if q.is_file():
            return q
    raise DataError("image listed in the transforms file not found (tried .png, .jpg, .jpeg)", p)


def _load_json(path: Path) -> dict:
    if not path.is_file():
        raise DataError("transforms file not found", path)
    try:
        with open(path) as f:
            return json.load(f)
    except (OSError, ValueError) as e:
        raise DataError(f"unreadable JSON: {e}", path) from e
