"""LLFF scenes: ``poses_bounds.npy`` + ``images[_N]/``.

``poses_bounds.npy`` is [V, 17]: a 3x5 matrix per view (camera→world rotation columns in
LLFF's "down, right, backward" axes, translation, then [height, width, focal] of the
full-resolution images) followed by the near/far depth bounds. Views are the image files
sorted by name, in the same order as the rows. The principal point is the image centre.

NeX's undistorted copies (``*_undistort``, the data the NVOS README points to) store
[V, 14]: the 3x4 pose (same axes) and the bounds, with the intrinsics of the
full-resolution images in ``hwf_cxcy.npy`` ([h, w, fx, fy, cx, cy], or [h, w, f] with the
principal point at the centre).

Views are named after ``images/`` (the full-resolution files) when a downscaled folder
names its files otherwise (``images_4/image000.png`` ... for ``IMG_4026.JPG`` ...): the two
are matched by sorted order, which needs the same count; ``Scene.notes`` says so.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from cobgs.render.camera import Camera
from cobgs.errors import DataError
from cobgs.data.images import list_images
from cobgs.data.scene import (
    Scene,
    View,
    finish_rgb,
    load_object_masks,
    make_scene,
    read_image_array,
    target_size,
)


def read_llff(
    path: os.PathLike | str,
    *,
    downscale: int = 8,
    test_every: int = 8,
    test_names: Optional[Sequence[str]] = None,
) -> Scene:
    """Read an LLFF scene.

    Args:
        path: folder with ``poses_bounds.npy`` and ``images_<downscale>/`` (or
            ``images/``, which is then resized in memory).
        downscale: integer factor; ``images_<downscale>/`` is used when it exists.
        test_every: hold out views 0, k, 2k, ... (sorted by name).
        test_names: explicit held-out views (image stems or file names).

    Returns:
        Scene without SfM points (LLFF ships none; run :mod:`cobgs.data.sfm` for them).
    """
    root = Path(path)
    pb_path = root / "poses_bounds.npy"
    if not pb_path.is_file():
        raise DataError("poses_bounds.npy not found", pb_path)
    try:
        pb = np.load(pb_path)
    except (OSError, ValueError) as e:
        raise DataError(f"unreadable numpy file: {e}", pb_path) from e
    notes: list[str] = []
    if pb.ndim == 2 and pb.shape[1] == 17:
        poses = pb[:, :15].reshape(-1, 3, 5).astype(np.float64)
        full = [(float(p[0, 4]), float(p[1, 4]), float(p[2, 4]), float(p[2, 4]), None, None)
                for p in poses]
        poses = poses[:, :, :4]
    elif pb.ndim == 2 and pb.shape[1] == 14:
        poses = pb[:, :12].reshape(-1, 3, 4).astype(np.float64)
        full = [_nex_intrinsics(root)] * len(poses)
        notes.append("NeX layout: 14-column poses_bounds.npy with the intrinsics of "
                     "hwf_cxcy.npy")
    else:
        raise DataError(f"expected a [V, 17] array (LLFF) or a [V, 14] one with hwf_cxcy.npy "
                        f"(NeX's *_undistort scenes), got {list(pb.shape)}", pb_path)

    folder = root / f"images_{int(downscale)}" if downscale != 1 else root / "images"
    resize = False
    if not folder.is_dir():
        if not (root / "images").is_dir():
            raise DataError(f"neither {folder.name}/ nor images/ found", root)
        folder, resize = root / "images", True
    files = list_images(folder)
    if len(files) != len(poses):
        raise DataError(
            f"{len(files)} images but poses_bounds.npy has {len(poses)} poses "
            "(one row per image, in sorted file order)",
            folder,
        )
    names = _view_names(root, folder, files, notes)
    views = []
    for f, name, pose, (full_h, full_w, fx0, fy0, cx0, cy0) in zip(files, names, poses, full):
        arr = read_image_array(f)
        native = (arr.shape[1], arr.shape[0])
        if abs(native[0] * full_h - native[1] * full_w) > 0.01 * full_w * native[1]:
            raise DataError(f"image is {native[0]}x{native[1]}, not of the aspect of the "
                            f"full-resolution {int(full_w)}x{int(full_h)} the poses were made "
                            f"for", f)
        size = target_size(full_w, full_h, downscale) if resize else native
        image, _ = finish_rgb(arr, size)
        # The intrinsics refer to the full-resolution image; scale them per axis.
        sx, sy = size[0] / full_w, size[1] / full_h
        fx, fy = fx0 * sx, fy0 * sy
        cx = size[0] / 2.0 if cx0 is None else cx0 * sx
        cy = size[1] / 2.0 if cy0 is None else cy0 * sy
        # LLFF rotation columns are (down, right, backward); OpenCV wants
        # (right, down, forward).
        R = pose[:, :3]
        c2w = np.eye(4)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2] = R[:, 1], R[:, 0], -R[:, 2]
        c2w[:3, 3] = pose[:, 3]
        w, h = size
        cam = Camera.from_c2w(c2w, fx, fy, cx, cy, w, h, name)
        masks, coverage = load_object_masks(root, name, size, (int(full_w), int(full_h)))
        views.append(View(cam, image, name, masks, coverage, os.fspath(f)))
    return make_scene(views, test_every=test_every, test_names=test_names, source=root, kind="llff",
                      notes=notes)


def _nex_intrinsics(root: Path) -> tuple:
    """(h, w, fx, fy, cx, cy) of NeX's hwf_cxcy.npy."""
    path = root / "hwf_cxcy.npy"
    if not path.is_file():
        raise DataError("a 14-column poses_bounds.npy (NeX's layout) needs hwf_cxcy.npy beside "
                        "it", path)
    try:
        a = np.load(path).astype(np.float64).reshape(-1)
    except (OSError, ValueError) as e:
        raise DataError(f"unreadable numpy file: {e}", path) from e
    if not np.isfinite(a).all():
        raise DataError(f"non-finite intrinsics {a.tolist()}", path)
    if a.size == 6:
        h, w, fx, fy, cx, cy = (float(v) for v in a)
    elif a.size == 3:
        h, w, fx = (float(v) for v in a)
        fy, cx, cy = fx, None, None
    else:
        raise DataError(f"expected [h, w, fx, fy, cx, cy] (or [h, w, f]), got {a.size} values",
                        path)
    if not (h > 0 and w > 0 and fx > 0 and fy > 0):
        raise DataError(f"sizes and focal lengths must be positive, got {a.tolist()}", path)
    return h, w, fx, fy, cx, cy


def _view_names(root: Path, folder: Path, files: list, notes: list[str]) -> list[str]:
    """View names: the file stems, or those of images/ (matched by sorted order) when the
    downscaled folder names its files otherwise."""
    stems = [f.stem for f in files]
    full = root / "images"
    if folder == full or not full.is_dir():
        return stems
    originals = [f.stem for f in list_images(full)]
    if originals == stems:
        return stems
    if len(originals) != len(stems):
        notes.append(f"{folder.name}/ and images/ name their files differently and hold "
                     f"{len(stems)} vs {len(originals)} images: views keep {folder.name}/'s "
                     f"names")
        return stems
    notes.append(f"{folder.name}/ names its images otherwise than images/ ({files[0].name} ... "
                 f"vs {originals[0]} ...): views take images/'s names, matched by sorted "
                 f"order")
    return originals
