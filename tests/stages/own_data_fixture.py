"""A user's own capture, as the tests need it: synthetic renders warped through a real lens
(COLMAP's SIMPLE_RADIAL model, k1 = -0.12: barrel distortion) and saved as JPEG photos in
``photos/images/``, with masks made for those distorted photos in
``photos/masks/ball/`` for the training views only: the held-out views have none (no
ground truth), as in a user's folder. The undistorted originals stay in ``synth/`` for
checks."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import numpy as np

from cobgs.data.synth.scene import generate_scene


def make(out, k1: float = -0.12, seed: int = 1, views: int = 16, w: int = 320, h: int = 240) -> Path:
    """Write the capture under ``out``; returns the photo folder (``out/photos``)."""
    out = Path(out)
    s = generate_scene(out / "synth", "demo", seed=seed, num_views=views, width_px=w, height_px=h, workers=2, progress=False)
    tf = json.loads((s / "transforms.json").read_text())
    f, cx, cy = tf["fl_x"], tf["cx"], tf["cy"]
    K = np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])
    # for every distorted pixel: its undistorted position (where to sample the pinhole render)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    pts = np.stack([xs.ravel() + 0.5, ys.ravel() + 0.5], 1)[:, None, :]
    und = cv2.undistortPoints(pts, K, np.array([k1, 0, 0, 0]), P=K)[:, 0, :]
    mx = (und[:, 0] - 0.5).reshape(h, w).astype(np.float32)
    my = (und[:, 1] - 0.5).reshape(h, w).astype(np.float32)
    root = out / "photos"
    (root / "images").mkdir(parents=True)
    (root / "masks" / "ball").mkdir(parents=True)
    names = sorted(p.name for p in (s / "images").iterdir())
    for i, n in enumerate(names):
        img = cv2.imread(str(s / "images" / n))
        cv2.imwrite(str(root / "images" / n.replace(".png", ".jpg")), cv2.remap(img, mx, my, cv2.INTER_LINEAR), [cv2.IMWRITE_JPEG_QUALITY, 95])
        if i % 8 != 0:
            m = cv2.imread(str(s / "masks" / "ball" / n), cv2.IMREAD_GRAYSCALE)
            cv2.imwrite(str(root / "masks" / "ball" / n), cv2.remap(m, mx, my, cv2.INTER_NEAREST))
    return root


if __name__ == "__main__":
    print(make(sys.argv[1]))
