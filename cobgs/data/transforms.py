"""NeRF-style ``transforms.json`` (instant-ngp / nerfstudio flavour) with per-object masks.

Layout and conventions: docs/data_formats.md. Intrinsics (``fl_x``, ``fl_y``, ``cx``,
``cy``, ``w``, ``h``) may be per frame (they win) or top level; ``camera_angle_x`` is
accepted when focal lengths are absent. Masks live in ``masks/<object>/<stem>.png``,
coverage maps (synthetic scenes) in ``coverage/<object>/<stem>.png``.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from ..camera import Camera
from ..errors import DataError
from .blender import _load_json
from .scene import (
    Scene,
    View,
    find_object_files,
    finish_rgb,
    make_scene,
    read_image_array,
    read_mask_array,
    resize_area,
    resize_mask,
    target_size,
)
from .undistort import undistort_view_arrays

_PINHOLE = ("PINHOLE", "SIMPLE_PINHOLE")
_DISTORTION_KEYS = ("k1", "k2", "p1", "p2")


def read_transforms(
    path: os.PathLike | str,
    *,
    downscale: float = 1.0,
    test_every: int = 8,
    test_names: Optional[Sequence[str]] = None,
    background: Sequence[float] = (0.0, 0.0, 0.0),
    filename: str = "transforms.json",
) -> Scene:
    """Read a NeRF-style scene with optional ``masks/<object>/`` folders.

    Args:
        path: folder holding ``transforms.json`` (or the JSON file itself).
        downscale: divide the image size by this.
        test_every: hold out every k-th frame (file order) when the file has no
            ``test_filenames`` and ``test_names`` is None.
        test_names: explicit held-out views (stems, file names or ``file_path`` s);
            overrides ``test_filenames`` from the file.
        background: compositing colour for RGBA images (also the training background).
        filename: JSON file name inside ``path``.

    Returns:
        Scene whose views carry ``masks`` (and ``coverage`` where present).
    """
    p = Path(path)
    jf = p if p.is_file() else p / filename
    root = jf.parent
    meta = _load_json(jf)
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise DataError("missing or empty 'frames' list", jf)
    views = [_read_frame(root, jf, meta, f, i, downscale, background) for i, f in enumerate(frames)]
    if test_names is None and meta.get("test_filenames") is not None:
        test_names = list(meta["test_filenames"])
    return make_scene(
        views,
        test_every=test_every,
        test_names=test_names,
        source=root,
        kind="transforms",
        background=tuple(float(b) for b in background),
    )


def _read_frame(root: Path, jf: Path, meta: dict, frame: dict, i: int, downscale, background) -> View:
    if not isinstance(frame, dict) or "file_path" not in frame or "transform_matrix" not in frame:
        raise DataError(f"frame {i} lacks 'file_path' or 'transform_matrix'", jf)
    img_path = root / frame["file_path"]
    if not img_path.is_file():
        raise DataError(f"image of frame {i} not found (listed in {jf.name})", img_path)

    def get(key, default=None):
        return frame.get(key, meta.get(key, default))

    arr = read_image_array(img_path)
    native = (arr.shape[1], arr.shape[0])
    w, h = int(get("w", native[0])), int(get("h", native[1]))
    if (w, h) != native:
        raise DataError(
            f"image is {native[0]}x{native[1]} but {jf.name} says w={w}, h={h} (frame {i})",
            img_path,
        )
    fx, fy = get("fl_x"), get("fl_y")
    if fx is None and get("camera_angle_x") is not None:
        fx = 0.5 * w / math.tan(0.5 * float(get("camera_angle_x")))
    if fx is None:
        raise DataError(f"frame {i}: no focal length ('fl_x' or 'camera_angle_x')", jf)
    if fy is None:
        ay = get("camera_angle_y")
        fy = fx if ay is None else 0.5 * h / math.tan(0.5 * float(ay))
    fx, fy = float(fx), float(fy)
    cx, cy = float(get("cx", w / 2.0)), float(get("cy", h / 2.0))
    model = str(get("camera_model", "PINHOLE")).upper()
    if model not in _PINHOLE and model != "OPENCV":
        raise DataError(
            f"frame {i}: unknown camera_model {model!r} (expected PINHOLE, SIMPLE_PINHOLE or OPENCV)",
            jf,
        )
    dist = [float(get(k, 0.0)) for k in _DISTORTION_KEYS]
    c2w = np.asarray(frame["transform_matrix"], np.float64)
    if c2w.shape not in ((4, 4), (3, 4)):
        raise DataError(f"frame {i}: transform_matrix must be 4x4, got {list(c2w.shape)}", jf)

    stem = img_path.stem
    size = target_size(*native, downscale)
    mask_files = find_object_files(root, stem, "masks")
    if model == "OPENCV" and any(d != 0.0 for d in dist):
        # Undistort pixels and masks at the native size first (masks must then be native).
        masks_native = {k: read_mask_array(f, [native]) for k, f in mask_files.items()}
        arr, masks_native, (fx, fy, cx, cy, w, h) = undistort_view_arrays(
            arr, masks_native, "OPENCV", [fx, fy, cx, cy, *dist], w, h, img_path
        )
        native = (w, h)
        size = target_size(*native, downscale)
    else:
        masks_native = {k: read_mask_array(f, [native, size]) for k, f in mask_files.items()}
    image, _ = finish_rgb(arr, size, background)
    cam = Camera.from_c2w(c2w, fx, fy, cx, cy, native[0], native[1], stem, opengl=True)
    cam = cam.resized(*size)
    masks = {k: resize_mask(m, size)[0] for k, m in masks_native.items()}
    coverage = {}
    for k, f in find_object_files(root, stem, "coverage").items():
        c = read_image_array(f)[:, :, 0]
        if (c.shape[1], c.shape[0]) not in (native, size):
            raise DataError(
                f"coverage map is {c.shape[1]}x{c.shape[0]}, expected {size[0]}x{size[1]}", f
            )
        coverage[k] = torch.from_numpy(np.ascontiguousarray(resize_area(c[:, :, None], *size)[:, :, 0]))
    return View(cam, image, stem, masks, coverage, os.fspath(img_path))
