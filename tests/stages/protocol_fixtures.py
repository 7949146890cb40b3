"""Small scenes in the published NVOS and LERF-mask layouts, made from a synthetic scene.

The synthetic generator knows the exact cameras and masks, so a scene written in another
layout keeps an exact ground truth: the protocols can then run end to end through the
pipeline and be checked against known answers.

* :func:`to_nvos` — an LLFF scene (``poses_bounds.npy`` + ``images_2/`` + ``masks/``) and
  an NVOS labels folder for one task (target = a held-out view, its GT mask at the
  "full" resolution, 2x the training images; scribbles at 1/4 of that).
* :func:`to_lerf_mask` — a COLMAP text model + ``images/`` + ``images_train/`` +
  ``test_mask/<idx>/<prompt>.png`` (+ ``masks/`` so the masks stage can read files).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np

GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def _frames(scene: Path):
    tf = json.loads((scene / "transforms.json").read_text())
    out = []
    for f in tf["frames"]:
        c2w = np.asarray(f["transform_matrix"], np.float64) @ GL_TO_CV  # OpenCV axes
        out.append((Path(f["file_path"]).stem, scene / f["file_path"], c2w, f))
    return out


def _copy_masks(scene: Path, out: Path, objects) -> None:
    for obj in objects:
        shutil.copytree(scene / "masks" / obj, out / "masks" / obj)


def to_nvos(scene: Path, out: Path, task: str, obj: str, target: str, reference: str,
            layout: str = "llff") -> tuple[Path, Path]:
    """Write ``out/llff`` and ``out/labels``; returns (scene folder, labels folder).

    ``layout``: "llff" (``poses_bounds.npy`` + ``images_2/`` named like the views);
    "nerf_llff_data" (the copy COB-GS, SAGA and FlashSplat evaluate on: COLMAP
    ``sparse/0`` with a SIMPLE_RADIAL camera over full-size ``images/<view>.JPG``, and
    ``images_2/image000.png`` ... in sorted order); "nex" (NeX's ``*_undistort``: a
    14-column ``poses_bounds.npy`` + ``hwf_cxcy.npy``, full-size ``images/``, and
    ``images_2/image000.png`` ...). Every layout also gets ``released_masks/<view>.JPG``:
    the object's mask of each view at the full size, JPEG-compressed, as COB-GS releases
    its NVOS masks.
    """
    llff, labels = out / "llff", out / "labels"
    (llff / "images_2").mkdir(parents=True)
    (llff / "released_masks").mkdir()
    frames = _frames(scene)
    rows, lines = [], []
    f0 = frames[0][3]
    for i, (stem, img, c2w, f) in enumerate(frames):
        renamed = layout in ("nerf_llff_data", "nex")
        shutil.copy(img, llff / "images_2" / (f"image{i:03d}.png" if renamed else f"{stem}.png"))
        big = cv2.resize(cv2.imread(str(img)), None, fx=2, fy=2, interpolation=cv2.INTER_LINEAR)
        if renamed:
            (llff / "images").mkdir(exist_ok=True)
            cv2.imwrite(str(llff / "images" / f"{stem}.JPG"), big)
        m = cv2.imread(str(scene / "masks" / obj / f"{stem}.png"), cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(str(llff / "released_masks" / f"{stem}.JPG"),
                    cv2.resize(m, None, fx=2, fy=2, interpolation=cv2.INTER_NEAREST))
        # LLFF columns: down, right, backward (then translation, then [h, w, focal] at full res).
        rot = np.stack([c2w[:3, 1], c2w[:3, 0], -c2w[:3, 2]], 1)
        if layout == "nex":
            rows.append(np.concatenate([np.column_stack([rot, c2w[:3, 3]]).ravel(), [0.5, 20.0]]))
        else:
            hwf = np.array([2 * f["h"], 2 * f["w"], 2 * f["fl_x"]])
            rows.append(np.concatenate([np.column_stack([rot, c2w[:3, 3], hwf]).ravel(), [0.5, 20.0]]))
        w2c = np.linalg.inv(c2w)
        q, t = _quat_wxyz(w2c[:3, :3]), w2c[:3, 3]
        lines.append(f"{i + 1} {' '.join(repr(float(v)) for v in q)} {' '.join(repr(float(v)) for v in t)} 1 {stem}.JPG\n\n")
    if layout == "nerf_llff_data":
        model = llff / "sparse" / "0"
        model.mkdir(parents=True)
        # SIMPLE_RADIAL at the full size (the images are pinhole renders: k1 tiny), as COLMAP
        # leaves it; the reference methods read it as a pinhole.
        (model / "cameras.txt").write_text(
            f"1 SIMPLE_RADIAL {2 * f0['w']} {2 * f0['h']} {2 * f0['fl_x']} {2 * f0['cx']} "
            f"{2 * f0['cy']} 0.0001\n")
        (model / "images.txt").write_text("".join(lines))
        (model / "points3D.txt").write_text("")
    else:
        np.save(llff / "poses_bounds.npy", np.stack(rows))
        if layout == "nex":
            np.save(llff / "hwf_cxcy.npy", np.array(
                [[2 * f0["h"]], [2 * f0["w"]], [2 * f0["fl_x"]], [2 * f0["fl_y"]], [2 * f0["cx"]],
                 [2 * f0["cy"]]]))
    _copy_masks(scene, llff, [obj])

    def up(a, k):
        return cv2.resize(a, None, fx=k, fy=k, interpolation=cv2.INTER_NEAREST)

    img_t = cv2.imread(str(scene / "images" / f"{target}.png"))
    img_r = cv2.imread(str(scene / "images" / f"{reference}.png"))
    gt = cv2.imread(str(scene / "masks" / obj / f"{target}.png"), cv2.IMREAD_GRAYSCALE)
    (labels / "masks" / task).mkdir(parents=True)
    (labels / "reference_image" / task).mkdir(parents=True)
    (labels / "scribbles" / task).mkdir(parents=True)
    cv2.imwrite(str(labels / "masks" / task / f"{target}.JPG"), up(img_t, 2))
    cv2.imwrite(str(labels / "masks" / task / f"{target}_mask.png"), up(gt, 2))
    cv2.imwrite(str(labels / "reference_image" / task / f"{reference}.JPG"), up(img_r, 2))
    # Scribbles at 1/4 of the "full" size = 1/2 of the training images: a stroke through the
    # object's centre and one on the background.
    ref = cv2.imread(str(scene / "masks" / obj / f"{reference}.png"), cv2.IMREAD_GRAYSCALE)
    small = cv2.resize(ref, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_NEAREST)
    ys, xs = np.nonzero(small)
    pos = np.zeros_like(small)
    cy, cx = int(ys.mean()), int(xs.mean())
    pos[cy, max(0, cx - 2): cx + 3] = 255
    neg = np.zeros_like(small)
    neg[1, 1:6] = 255
    cv2.imwrite(str(labels / "scribbles" / task / "pos_0.png"), pos)
    cv2.imwrite(str(labels / "scribbles" / task / "neg_0.png"), neg)
    return llff, labels


def _quat_wxyz(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix (Shepperd's method)."""
    t = np.trace(r)
    if t > 0:
        s = 2.0 * np.sqrt(t + 1.0)
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(r)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + r[i, i] - r[j, j] - r[k, k])
        q = [0.0] * 4
        q[0] = (r[k, j] - r[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (r[j, i] + r[i, j]) / s
        q[1 + k] = (r[k, i] + r[i, k]) / s
    q = np.asarray(q)
    return q / np.linalg.norm(q)


def to_lerf_mask(scene: Path, out: Path, prompts: dict[str, str], test_every: int = 4) -> tuple[Path, list[str]]:
    """Write a LERF-mask scene; ``prompts`` maps prompt -> synthetic object. Returns
    (folder, test view stems in protocol order)."""
    frames = _frames(scene)
    (out / "images").mkdir(parents=True)
    (out / "images_train").mkdir()
    model = out / "sparse" / "0"
    model.mkdir(parents=True)
    f0 = frames[0][3]
    (model / "cameras.txt").write_text(
        f"1 PINHOLE {f0['w']} {f0['h']} {f0['fl_x']} {f0['fl_y']} {f0['cx']} {f0['cy']}\n")
    lines, test = [], []
    for i, (stem, img, c2w, _) in enumerate(frames):
        name = f"frame_{stem}.png"
        shutil.copy(img, out / "images" / name)
        if i % test_every == 0:
            test.append(f"frame_{stem}")
        else:
            shutil.copy(img, out / "images_train" / name)
        w2c = np.linalg.inv(c2w)
        q, t = _quat_wxyz(w2c[:3, :3]), w2c[:3, 3]
        lines.append(f"{i + 1} {' '.join(repr(float(v)) for v in q)} {' '.join(repr(float(v)) for v in t)} 1 {name}\n\n")
    (model / "images.txt").write_text("".join(lines))
    (model / "points3D.txt").write_text("")
    test = sorted(test)
    for prompt, obj in prompts.items():
        d = out / "masks" / prompt
        d.mkdir(parents=True)
        for stem, *_ in frames:
            shutil.copy(scene / "masks" / obj / f"{stem}.png", d / f"frame_{stem}.png")
        for idx, view in enumerate(test):
            g = out / "test_mask" / str(idx)
            g.mkdir(parents=True, exist_ok=True)
            shutil.copy(scene / "masks" / obj / f"{view[len('frame_'):]}.png", g / f"{prompt}.png")
    return out, test
