"""COLMAP scenes (binary or text models) read through pycolmap.

Layout: ``<scene>/images/`` and a model in ``<scene>/sparse/0/``, ``<scene>/sparse/`` or
``<scene>/`` itself (cameras/images/points3D as ``.bin`` or ``.txt``). Views are the
registered images sorted by name. Cameras with a distorted model are undistorted to
PINHOLE at load time (see :mod:`cobgs.data.undistort`); PINHOLE and SIMPLE_PINHOLE
images are used as they are. Optional masks: ``<scene>/masks/<object>/<stem>.png``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from cobgs.render.camera import Camera
from cobgs.errors import DataError
from cobgs.data.images import list_images
from cobgs.data.scene import (
    Scene,
    View,
    find_object_files,
    finish_rgb,
    make_scene,
    read_image_array,
    read_mask_array,
    resize_mask,
    target_size,
)
from cobgs.data.undistort import DROPPABLE_MODELS, PINHOLE_MODELS, split_pinhole, undistort_view_arrays



def find_model_dir(root: os.PathLike | str) -> Path:
    """The folder holding the COLMAP model under ``root`` (sparse/0, sparse, or root)."""
    from cobgs.data.layout import colmap_model_dir

    found = colmap_model_dir(root)
    if found is not None:
        return found
    raise DataError(
        "no COLMAP model found (expected cameras, images, points3D as .bin or .txt in "
        "sparse/0/, sparse/ or the scene folder)",
        root,
    )


def read_colmap(
    path: os.PathLike | str,
    *,
    images_dir: Optional[os.PathLike | str] = None,
    model_dir: Optional[os.PathLike | str] = None,
    downscale: float = 1.0,
    test_every: int = 8,
    test_names: Optional[Sequence[str]] = None,
    distortion: str = "auto",
) -> Scene:
    """Read a COLMAP scene.

    Args:
        path: scene folder.
        images_dir: image folder (default ``<path>/images``); image names in the model
            are relative to it.
        model_dir: model folder (default: found by :func:`find_model_dir`).
        downscale: divide the image size by this. When ``<path>/images_<k>/`` exists for
            an integer ``downscale == k`` and ``images_dir`` is not given, those
            pre-shrunk images are used (the LLFF / Mip-NeRF 360 convention).
            When the files there are named otherwise than the model's images (LLFF's
            ``nerf_llff_data``: ``images_4/image000.png`` ... for ``IMG_4026.JPG`` ...),
            they are matched to the model's images by sorted order, which needs the same
            number of images (and each matched image must have the camera's aspect).
        test_every: hold out views 0, k, 2k, ... of the name-sorted registered images.
        test_names: explicit held-out views (stems or file names).
        distortion: what to do with a distorted camera model. "undistort": remap the
            full-size images (a pre-shrunk ``images_<k>/`` is then refused); "ignore": read
            SIMPLE_RADIAL / RADIAL / OPENCV / FULL_OPENCV cameras as their pinhole, the
            distortion terms dropped (what the NVOS reference methods do with
            ``nerf_llff_data``'s SIMPLE_RADIAL camera); "auto" (default): undistort when
            the full-size images are used, ignore with pre-shrunk ones. Every dropped term
            is listed in ``Scene.notes``.

    Returns:
        Scene with SfM ``points`` / ``points_rgb`` from the model.
    """
    from cobgs.data.pycolmap_import import import_pycolmap

    pycolmap = import_pycolmap()

    if distortion not in ("auto", "undistort", "ignore"):
        raise DataError(f"distortion must be 'auto', 'undistort' or 'ignore', got {distortion!r}",
                        path)
    root = Path(path)
    mdir = Path(model_dir) if model_dir is not None else find_model_dir(root)
    try:
        rec = pycolmap.Reconstruction(mdir)
    except Exception as e:  # pycolmap reports parse errors as generic exceptions
        raise DataError(f"unreadable COLMAP model: {e}", mdir) from e

    pre_shrunk = False
    if images_dir is not None:
        idir = Path(images_dir)
    else:
        idir = root / "images"
        k = int(round(downscale))
        if downscale != 1 and abs(downscale - k) < 1e-9 and (root / f"images_{k}").is_dir():
            idir, pre_shrunk = root / f"images_{k}", True
    if not idir.is_dir():
        raise DataError("image folder not found", idir)

    notes: list[str] = []
    every = sorted(rec.images.values(), key=lambda im: im.name)
    files = _match_image_files(idir, [im.name for im in every], pre_shrunk, mdir, notes)
    images = [im for im in every if _has_pose(im)]
    if not images:
        raise DataError("the model has no registered images", mdir)
    drop = distortion == "ignore" or (distortion == "auto" and pre_shrunk)
    views = [_read_view(root, rec, im, files[im.name], downscale, pre_shrunk, drop, notes)
             for im in images]

    pts = rec.points3D
    points = points_rgb = None
    if len(pts) > 0:
        ids = sorted(pts.keys())
        points = torch.tensor(np.stack([pts[i].xyz for i in ids]), dtype=torch.float32)
        points_rgb = torch.tensor(np.stack([pts[i].color for i in ids]), dtype=torch.float32) / 255.0
    return make_scene(
        views,
        test_every=test_every,
        test_names=test_names,
        source=root,
        kind="colmap",
        points=points,
        points_rgb=points_rgb,
        notes=notes,
    )


def _match_image_files(idir: Path, names: list[str], pre_shrunk: bool, mdir: Path,
                       notes: list[str]) -> dict[str, Path]:
    """The file of each of the model's images: ``idir/<name>``, or, for a pre-shrunk folder
    whose files are named otherwise (nerf_llff_data's ``images_4/image000.png``), the file
    at the same position in sorted order."""
    direct = {n: idir / n for n in names}
    if not pre_shrunk or all(p.is_file() for p in direct.values()):
        return direct
    files = list_images(idir)
    if any(p.is_file() for p in direct.values()) or len(files) != len(names):
        missing = [n for n, p in direct.items() if not p.is_file()]
        raise DataError(
            f"{idir.name}/ does not hold the model's images under their names (missing e.g. "
            f"{missing[:3]}), and it cannot be matched to them by sorted order: it has "
            f"{len(files)} images, the model {len(names)} ({mdir}); pass images_dir, or give "
            f"{idir.name}/ the model's file names", idir)
    notes.append(f"{idir.name}/ names its images otherwise than the COLMAP model "
                 f"({files[0].name} ... vs {names[0]} ...): matched by sorted order, "
                 f"{len(files)} images")
    return dict(zip(names, files))


def _has_pose(im) -> bool:
    has = getattr(im, "has_pose", None)
    if has is None:
        return True
    return bool(has() if callable(has) else has)


def _read_view(root: Path, rec, im, img_path: Path, downscale: float, pre_shrunk: bool,
               drop_distortion: bool, notes: list[str]) -> View:
    cam = rec.cameras[im.camera_id]
    model = cam.model.name
    if not img_path.is_file():
        raise DataError(f"image {im.name!r} of the COLMAP model not found", img_path)
    arr = read_image_array(img_path)
    got = (arr.shape[1], arr.shape[0])
    cam_size = (int(cam.width), int(cam.height))
    params = [float(p) for p in cam.params]
    stem = Path(im.name).stem
    mask_files = find_object_files(root, stem, "masks")

    if pre_shrunk:
        # images_<k>/ holds the images already shrunk; rescale the camera to them.
        expect = target_size(*cam_size, downscale)
        if abs(got[0] - expect[0]) > 1 or abs(got[1] - expect[1]) > 1:
            raise DataError(
                f"image is {got[0]}x{got[1]}, expected about {expect[0]}x{expect[1]} "
                f"(camera {cam_size[0]}x{cam_size[1]} of {im.name} / {downscale}: another "
                f"aspect or size)",
                img_path,
            )
    elif got != cam_size:
        raise DataError(
            f"image is {got[0]}x{got[1]} but camera {im.camera_id} ({model}) is "
            f"{cam_size[0]}x{cam_size[1]}",
            img_path,
        )

    dropped = drop_distortion and model in DROPPABLE_MODELS
    if model in PINHOLE_MODELS or dropped:
        (fx, fy, cx, cy), terms = split_pinhole(model, params)
        if dropped:
            note = (f"camera {im.camera_id} ({model}) read as a pinhole, distortion "
                    f"{[round(t, 6) for t in terms]} dropped (as the NVOS reference methods "
                    f"read nerf_llff_data)")
            if note not in notes:
                notes.append(note)
        native = got
        sx, sy = got[0] / cam_size[0], got[1] / cam_size[1]
        fx, fy, cx, cy = fx * sx, fy * sy, cx * sx, cy * sy
        size = native if pre_shrunk else target_size(*native, downscale)
        masks_native = {k: read_mask_array(f, [native, size]) for k, f in mask_files.items()}
    else:
        if pre_shrunk:
            raise DataError(
                f"camera model {model} is distorted; undistortion needs the full-size images, "
                "not a pre-shrunk images_<k>/ folder (pass images_dir, or distortion = "
                "'ignore' to read it as a pinhole where the model allows)",
                img_path,
            )
        masks_native = {k: read_mask_array(f, [got]) for k, f in mask_files.items()}
        arr, masks_native, (fx, fy, cx, cy, w, h) = undistort_view_arrays(
            arr, masks_native, model, params, cam_size[0], cam_size[1], img_path
        )
        native = (w, h)
        size = target_size(*native, downscale)
    image, _ = finish_rgb(arr, size)
    R_t = _cam_from_world(im)
    c2w = np.linalg.inv(R_t)
    camera = Camera.from_c2w(c2w, fx, fy, cx, cy, native[0], native[1], stem).resized(*size)
    masks = {k: resize_mask(m, size)[0] for k, m in masks_native.items()}
    return View(camera, image, stem, masks, {}, os.fspath(img_path))


def _cam_from_world(im) -> np.ndarray:
    """[4, 4] world→camera of a pycolmap image (COLMAP uses OpenCV axes already)."""
    pose = im.cam_from_world
    if callable(pose):
        pose = pose()
    m = np.eye(4)
    m[:3, :4] = np.asarray(pose.matrix(), np.float64)
    return m
