"""LLFF scenes: ``poses_bounds.npy`` + ``images[_N]/``.

``poses_bounds.npy`` is [V, 17]: a 3x5 matrix per view (camera→world rotation columns in
LLFF's "down, right, backward" axes, translation, then [height, width, focal] of the
full-resolution images) followed by the near/far depth bounds. Views are the image files
sorted by name, in the same order as the rows. The principal point is the image centre.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from ..camera import Camera
from ..errors import DataError
from .scene import (
    Scene,
    View,
    finish_rgb,
    list_images,
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
        Scene without SfM points (LLFF ships none; run :mod:`cobgs.sfm` for them).
    """
    root = Path(path)
    pb_path = root / "poses_bounds.npy"
    if not pb_path.is_file():
        raise DataError("poses_bounds.npy not found", pb_path)
    try:
        pb = np.load(pb_path)
    except (OSError, ValueError) as e:
        raise DataError(f"unreadable numpy file: {e}", pb_path) from e
    if pb.ndim != 2 or pb.shape[1] != 17:
        raise DataError(f"expected a [V, 17] array, got {list(pb.shape)}", pb_path)
    poses = pb[:, :15].reshape(-1, 3, 5).astype(np.float64)

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
    views = []
    for f, pose in zip(files, poses):
        full_h, full_w, focal = pose[:, 4]
        arr = read_image_array(f)
        native = (arr.shape[1], arr.shape[0])
        size = target_size(full_w, full_h, downscale) if resize else native
        image, _ = finish_rgb(arr, size)
        # The focal length refers to the full-resolution image; scale it per axis.
        fx, fy = focal * size[0] / full_w, focal * size[1] / full_h
        # LLFF rotation columns are (down, right, backward); OpenCV wants
        # (right, down, forward).
        R = pose[:, :3]
        c2w = np.eye(4)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2] = R[:, 1], R[:, 0], -R[:, 2]
        c2w[:3, 3] = pose[:, 3]
        w, h = size
        cam = Camera.from_c2w(c2w, fx, fy, w / 2.0, h / 2.0, w, h, f.stem)
        masks, coverage = load_object_masks(root, f.stem, size, (int(full_w), int(full_h)))
        views.append(View(cam, image, f.stem, masks, coverage, os.fspath(f)))
    return make_scene(views, test_every=test_every, test_names=test_names, source=root, kind="llff")
