"""NeRF-style ``transforms.json`` (instant-ngp / nerfstudio flavour) with per-object masks.

Layout and conventions: docs/data_formats.md. Intrinsics (``fl_x``, ``fl_y``, ``cx``,
``cy``, ``w``, ``h``) may be per frame (they win) or top level; ``camera_angle_x`` is
accepted when focal lengths are absent. Distortion as nerfstudio writes it (OPENCV: k1 k2
p1 p2, with k3 the full OpenCV model; OPENCV_FISHEYE: k1..k4) is undistorted; terms the
model cannot hold, and ``distortion_params``, are refused naming the key. nerfstudio's
``ply_file_path`` point cloud becomes the scene's initial points. Masks live in ``masks/<object>/<stem>.png``,
coverage maps (synthetic scenes) in ``coverage/<object>/<stem>.png``.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from cobgs.render.camera import Camera
from cobgs.errors import DataError
from cobgs.data.blender import _load_json, check_pose, resolve_image
from cobgs.data.scene import (
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
from cobgs.data.undistort import undistort_view_arrays

_PINHOLE = ("PINHOLE", "SIMPLE_PINHOLE")
_MODELS = (*_PINHOLE, "OPENCV", "OPENCV_FISHEYE")
_ALL_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")


def _distortion(get, model: str, i: int, jf: Path) -> tuple[str, list[float]]:
    """(COLMAP model, its distortion parameters after fx, fy, cx, cy) of a frame, as
    nerfstudio writes them: OPENCV k1 k2 p1 p2 (+ k3: the full OpenCV model), OPENCV_FISHEYE
    k1..k4. A term the model cannot hold, or ``distortion_params`` (whose order no format
    fixes), is refused naming the key rather than ignored."""
    d = {}
    for k in _ALL_DISTORTION_KEYS:
        try:
            d[k] = float(get(k, 0.0) or 0.0)
        except (TypeError, ValueError):
            raise DataError(f"frame {i}: distortion term {k!r} must be a number, got "
                            f"{get(k)!r}", jf) from None
        if not math.isfinite(d[k]):
            raise DataError(f"frame {i}: distortion term {k!r} is {d[k]}", jf)
    given = [k for k, v in d.items() if v != 0.0]
    dp = get("distortion_params")
    try:
        dp_given = dp is not None and any(float(v) != 0.0 for v in dp)
    except (TypeError, ValueError):
        raise DataError(f"frame {i}: 'distortion_params' must be a list of numbers, got {dp!r}",
                        jf) from None
    if dp_given:
        raise DataError(f"frame {i}: 'distortion_params' {list(dp)} is not read (its order differs "
                        f"between tools); give the terms as k1, k2, k3, k4, p1, p2 with "
                        f"camera_model OPENCV or OPENCV_FISHEYE", jf)
    if model in _PINHOLE:
        if given:
            raise DataError(f"frame {i}: camera_model {model} but distortion {given} is given "
                            f"(set camera_model OPENCV, or OPENCV_FISHEYE, to apply it)", jf)
        return model, []
    if model == "OPENCV_FISHEYE":
        bad = [k for k in ("p1", "p2") if d[k] != 0.0]
        if bad:
            raise DataError(f"frame {i}: OPENCV_FISHEYE has no tangential terms, got {bad}", jf)
        return "OPENCV_FISHEYE", [d["k1"], d["k2"], d["k3"], d["k4"]]
    if d["k4"] != 0.0:
        raise DataError(f"frame {i}: k4 = {d['k4']} with camera_model OPENCV (k4 belongs to "
                        f"OPENCV_FISHEYE in nerfstudio's convention); set camera_model, or drop "
                        f"k4", jf)
    if d["k3"] != 0.0:  # the full OpenCV model: k1 k2 p1 p2 k3 (k4..k6 of the rational model 0)
        return "FULL_OPENCV", [d["k1"], d["k2"], d["p1"], d["p2"], d["k3"], 0.0, 0.0, 0.0]
    return "OPENCV", [d["k1"], d["k2"], d["p1"], d["p2"]]


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
    seen: dict[str, int] = {}
    for i, f in enumerate(frames):
        key = Path(str(f.get("file_path", ""))).as_posix() if isinstance(f, dict) else ""
        if key and key in seen:
            raise DataError(f"frame {i} repeats frame {seen[key]}'s file_path {key!r} (each image "
                            "must appear once)", jf)
        seen[key] = i
    views = [_read_frame(root, jf, meta, f, i, downscale, background) for i, f in enumerate(frames)]
    if test_names is None and meta.get("test_filenames") is not None:
        test_names = list(meta["test_filenames"])
    points = points_rgb = None
    notes = []
    if meta.get("ply_file_path"):
        points, points_rgb = _read_point_cloud(root / str(meta["ply_file_path"]), jf)
        notes.append(f"initial points: {len(points)} from {meta['ply_file_path']} (ply_file_path)")
    return make_scene(
        views,
        test_every=test_every,
        test_names=test_names,
        source=root,
        kind="transforms",
        background=tuple(float(b) for b in background),
        points=points,
        points_rgb=points_rgb,
        notes=notes,
    )


def _read_point_cloud(path: Path, jf: Path) -> tuple[torch.Tensor, torch.Tensor]:
    """x, y, z and (when present) 8-bit red, green, blue of a point-cloud PLY (nerfstudio's
    ``ply_file_path``, in the frames' world coordinates)."""
    from plyfile import PlyData

    if not path.is_file():
        raise DataError(f"ply_file_path of {jf.name} names a missing file", path)
    try:
        v = PlyData.read(os.fspath(path))["vertex"].data
    except Exception as e:  # plyfile raises several types
        raise DataError(f"unreadable point cloud (ply_file_path of {jf.name}): {e}", path) from e
    names = v.dtype.names or ()
    if not all(c in names for c in "xyz"):
        raise DataError(f"point cloud without x, y, z (properties: {list(names)})", path)
    xyz = np.stack([np.asarray(v[c], np.float64) for c in "xyz"], 1)
    finite = np.isfinite(xyz).all(1)
    if not finite.all():
        raise DataError(f"{int((~finite).sum())} of {len(xyz)} points have non-finite coordinates",
                        path)
    if all(c in names for c in ("red", "green", "blue")):
        rgb = np.stack([np.asarray(v[c], np.float64) for c in ("red", "green", "blue")], 1) / 255.0
    else:
        rgb = np.full_like(xyz, 0.5)
    return (torch.tensor(xyz, dtype=torch.float32),
            torch.tensor(np.clip(rgb, 0.0, 1.0), dtype=torch.float32))


def _read_frame(root: Path, jf: Path, meta: dict, frame: dict, i: int, downscale, background) -> View:
    if not isinstance(frame, dict) or "file_path" not in frame or "transform_matrix" not in frame:
        raise DataError(f"frame {i} lacks 'file_path' or 'transform_matrix'", jf)
    try:
        img_path = resolve_image(root, str(frame["file_path"]))
    except DataError:
        raise DataError(f"image of frame {i} not found (listed in {jf.name}; a path without an "
                        "extension is tried as .png / .jpg)", root / str(frame["file_path"])) from None

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
    def number(key, default=None, positive=False, below=None):
        v = get(key, default)
        if v is None:
            return None
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise DataError(f"frame {i} ({frame['file_path']}): {key!r} must be a number, got {v!r}", jf)
        v = float(v)
        if not math.isfinite(v) or (positive and v <= 0) or (below is not None and v >= below):
            want = "a finite number" + (" > 0" if positive else "") + (f" < {below:.4g}" if below else "")
            raise DataError(f"frame {i} ({frame['file_path']}): {key!r} is {v}, expected {want}", jf)
        return v

    fx, fy = number("fl_x", positive=True), number("fl_y", positive=True)
    ax = number("camera_angle_x", positive=True, below=math.pi)
    if fx is None and ax is not None:
        fx = 0.5 * w / math.tan(0.5 * ax)
    if fx is None:
        raise DataError(f"frame {i}: no focal length ('fl_x' or 'camera_angle_x')", jf)
    if fy is None:
        ay = number("camera_angle_y", positive=True, below=math.pi)
        fy = fx if ay is None else 0.5 * h / math.tan(0.5 * ay)
    cx, cy = number("cx", w / 2.0), number("cy", h / 2.0)
    model = str(get("camera_model", "PINHOLE")).upper()
    if model not in _MODELS:
        raise DataError(
            f"frame {i}: unknown camera_model {model!r} (expected one of {list(_MODELS)})",
            jf,
        )
    model, dist = _distortion(get, model, i, jf)
    c2w = check_pose(frame["transform_matrix"], f"frame {i} ({frame['file_path']})", jf)

    stem = img_path.stem
    size = target_size(*native, downscale)
    mask_files = find_object_files(root, stem, "masks")
    if any(d != 0.0 for d in dist):
        # Undistort pixels and masks at the native size first (masks must then be native).
        masks_native = {k: read_mask_array(f, [native]) for k, f in mask_files.items()}
        arr, masks_native, (fx, fy, cx, cy, w, h) = undistort_view_arrays(
            arr, masks_native, model, [fx, fy, cx, cy, *dist], w, h, img_path
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
