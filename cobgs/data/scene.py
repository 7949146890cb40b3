"""The one scene model every reader returns, plus image / mask loading and the split.

A :class:`Scene` is a list of training and held-out :class:`View` s (camera, float32 RGB
image, optional per-object masks), optional SfM points and the scene extent (NeRF++
radius of the training cameras, the scale 3DGS multiplies its thresholds by).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import cv2
import numpy as np
import torch
from torch import Tensor

from cobgs.render.camera import Camera, scene_extent
from cobgs.data.images import IMAGE_EXTENSIONS
from cobgs.errors import DataError, InputError



@dataclass
class View:
    """One image with its camera.

    Attributes:
        camera: the pinhole camera of this image (its size matches ``image``).
        image: [H, W, 3] float32 RGB in [0, 1] (RGBA sources already composited).
        name: image file stem (``camera.name`` too).
        masks: object name → [H, W] bool mask; only objects annotated in this view.
        coverage: object name → [H, W] float32 fraction of the pixel covered by the object,
            where the source provides it (synthetic scenes, Blender alpha).
        path: the image file it was read from.
    """

    camera: Camera
    image: Tensor
    name: str
    masks: dict[str, Tensor] = field(default_factory=dict)
    coverage: dict[str, Tensor] = field(default_factory=dict)
    path: Optional[str] = None

    @property
    def width(self) -> int:
        return self.camera.width

    @property
    def height(self) -> int:
        return self.camera.height


@dataclass
class Scene:
    """A set of posed images ready for training and evaluation.

    Attributes:
        train: training views.
        test: held-out views (may be empty).
        extent: NeRF++ radius of the training cameras (world units).
        points: [P, 3] float32 SfM points, or None (train then initialises randomly).
        points_rgb: [P, 3] float32 colours of ``points`` in [0, 1], or None.
        init_bounds: (lo [3], hi [3]) box for random initialisation when there are no
            points; None lets the trainer derive one from the cameras.
        background: RGB in [0, 1] that RGBA images were composited on; the trainer
            renders on the same colour (black for opaque captures, as in 3DGS).
        object_names: every object with masks in at least one view, sorted.
        source: folder the scene was read from.
        kind: which reader produced it ("colmap", "llff", "blender", "transforms").
        notes: what the reader decided that a user should know (e.g. a distortion model
            read as a pinhole, images matched to poses by sorted order); the dataset
            stage writes them into its manifest.
    """

    train: list[View]
    test: list[View]
    extent: float
    points: Optional[Tensor] = None
    points_rgb: Optional[Tensor] = None
    init_bounds: Optional[tuple[list[float], list[float]]] = None
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    object_names: list[str] = field(default_factory=list)
    source: str = ""
    kind: str = ""
    notes: list[str] = field(default_factory=list)

    @property
    def views(self) -> list[View]:
        return list(self.train) + list(self.test)


def make_scene(
    views: list[View],
    *,
    test_every: int = 8,
    test_names: Optional[Sequence[str]] = None,
    source: os.PathLike | str = "",
    kind: str = "",
    **extra,
) -> Scene:
    """Split ``views`` (already in their canonical order) and build a :class:`Scene`."""
    train, test = split_views(views, test_every=test_every, test_names=test_names, source=source)
    if not train:
        raise DataError("no training views left after the train/test split", source)
    names = sorted({k for v in views for k in v.masks})
    return Scene(
        train=train,
        test=test,
        extent=scene_extent([v.camera for v in train]),
        object_names=names,
        source=os.fspath(source),
        kind=kind,
        **extra,
    )


def split_views(
    views: list[View],
    *,
    test_every: int = 8,
    test_names: Optional[Sequence[str]] = None,
    source: os.PathLike | str = "",
) -> tuple[list[View], list[View]]:
    """Split views into (train, test).

    Args:
        views: views in canonical order (sorted by name for folder-based readers).
        test_every: hold out views 0, k, 2k, ... (the 3DGS / LLFF convention); 0 or less
            holds out nothing. Ignored when ``test_names`` is given.
        test_names: explicit held-out views, each matched against the view's stem, its
            file name or its path relative to the scene (``images/0007.png``).
        source: scene folder, for error messages.
    """
    if test_names is not None:
        wanted = {_norm(n) for n in test_names}
        keys = [_view_keys(v, source) for v in views]
        found = set().union(*keys) if keys else set()
        missing = sorted(n for n in wanted if n not in found)
        if missing:
            raise DataError(
                f"held-out view(s) {missing} are not among the {len(views)} images "
                f"(expected image stems or file names such as {views[0].name!r})"
                if views
                else f"held-out view(s) {missing} requested but the scene has no images",
                source,
            )
        is_test = [bool(k & wanted) for k in keys]
    elif test_every and test_every > 0:
        is_test = [i % test_every == 0 for i in range(len(views))]
    else:
        is_test = [False] * len(views)
    train = [v for v, t in zip(views, is_test) if not t]
    test = [v for v, t in zip(views, is_test) if t]
    return train, test


def _norm(name: str) -> str:
    s = str(name).replace("\\", "/")
    while s.startswith("./"):
        s = s[2:]
    return s


def _view_keys(view: View, source) -> set[str]:
    keys = {view.name}
    if view.path:
        p = Path(view.path)
        keys.add(p.name)
        try:
            keys.add(p.relative_to(Path(source)).as_posix())
        except ValueError:
            pass
    return keys


# -- pixels ---------------------------------------------------------------------------------
def read_image_array(path: os.PathLike | str) -> np.ndarray:
    """Read an image file as float32 [H, W, C] in [0, 1] (C = 1, 3 or 4; RGB(A) order)."""
    path = Path(path)
    if not path.is_file():
        raise DataError("image file not found", path)
    arr = cv2.imread(os.fspath(path), cv2.IMREAD_UNCHANGED)
    if arr is None:
        raise DataError("unreadable image (not a format OpenCV can decode, or truncated)", path)
    if arr.dtype == np.uint8:
        scale = 255.0
    elif arr.dtype == np.uint16:
        scale = 65535.0
    elif arr.dtype in (np.float32, np.float64):
        scale = 1.0
    else:
        raise DataError(f"unsupported pixel type {arr.dtype} (expected 8/16-bit or float)", path)
    arr = arr.astype(np.float32) / scale
    if arr.ndim == 2:
        arr = arr[:, :, None]
    if arr.shape[2] == 3:
        arr = arr[:, :, ::-1]
    elif arr.shape[2] == 4:
        arr = arr[:, :, [2, 1, 0, 3]]
    elif arr.shape[2] != 1:
        raise DataError(f"expected 1, 3 or 4 channels, got {arr.shape[2]}", path)
    return np.ascontiguousarray(arr)


def resize_area(arr: np.ndarray, width: int, height: int) -> np.ndarray:
    """Area-filtered resize of [H, W, C] float32 (box average when shrinking)."""
    if arr.shape[1] == width and arr.shape[0] == height:
        return arr
    out = cv2.resize(arr, (int(width), int(height)), interpolation=cv2.INTER_AREA)
    if out.ndim == 2:
        out = out[:, :, None]
    return out


def finish_rgb(
    arr: np.ndarray,
    size: Optional[tuple[int, int]],
    background: Sequence[float] = (0.0, 0.0, 0.0),
) -> tuple[Tensor, Optional[Tensor]]:
    """Resize decoded pixels (area filter) and composite RGBA on ``background``.

    Args:
        arr: [H, W, C] float32 in [0, 1], C = 1, 3 or 4 (from :func:`read_image_array`).
        size: (width, height) to resize to, or None for the native size.
        background: RGB in [0, 1] for RGBA images.

    Returns:
        (image [h, w, 3] float32, alpha [h, w] float32 or None for opaque images).
    """
    alpha = None
    if arr.shape[2] == 4:
        # Premultiply before filtering so that transparent pixels' colours do not bleed;
        # then C = C_pm + bg (1 - a).
        arr = np.concatenate([arr[:, :, :3] * arr[:, :, 3:], arr[:, :, 3:]], 2)
        if size is not None:
            arr = resize_area(arr, *size)
        alpha = arr[:, :, 3]
        bg = np.asarray(background, np.float32).reshape(1, 1, 3)
        rgb = arr[:, :, :3] + bg * (1.0 - alpha[:, :, None])
    else:
        if size is not None:
            arr = resize_area(arr, *size)
        rgb = np.repeat(arr, 3, axis=2) if arr.shape[2] == 1 else arr
    img = torch.from_numpy(np.ascontiguousarray(np.clip(rgb, 0.0, 1.0), dtype=np.float32))
    return img, None if alpha is None else torch.from_numpy(np.ascontiguousarray(alpha))


def load_rgb(
    path: os.PathLike | str,
    size: Optional[tuple[int, int]] = None,
    background: Sequence[float] = (0.0, 0.0, 0.0),
) -> tuple[Tensor, Optional[Tensor]]:
    """:func:`read_image_array` then :func:`finish_rgb` (same arguments and returns)."""
    return finish_rgb(read_image_array(path), size, background)


def read_mask_array(path: os.PathLike | str, allowed_sizes: Sequence[tuple[int, int]]) -> np.ndarray:
    """Read a mask as a binary float32 [H, W] array, checking its size.

    Pixels count as object where the grey level is at least half of full scale (JPEG
    noise near 0 is not foreground); colour masks use their first channel.

    Args:
        path: mask image.
        allowed_sizes: acceptable (width, height) pairs (the training and the source size).
    """
    arr = read_image_array(path)[:, :, 0]
    got = (arr.shape[1], arr.shape[0])
    allowed = {tuple(int(x) for x in s) for s in allowed_sizes}
    if got not in allowed:
        want = " or ".join(f"{w}x{h}" for w, h in sorted(allowed))
        raise DataError(f"mask is {got[0]}x{got[1]}, expected {want} (the image size)", path)
    return (arr >= 0.5).astype(np.float32)


def resize_mask(binary: np.ndarray, size: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """Area-average a binary [H, W] mask to ``size``.

    Returns:
        (mask [h, w] bool: covered fraction >= 0.5, coverage [h, w] float32 fraction).
    """
    cov = resize_area(np.asarray(binary, np.float32)[:, :, None], *size)[:, :, 0]
    return torch.from_numpy(cov >= 0.5), torch.from_numpy(np.ascontiguousarray(cov))


def target_size(width: int, height: int, downscale: float) -> tuple[int, int]:
    """Image size after dividing by ``downscale`` (rounded, at least 1 pixel)."""
    if downscale <= 0:
        raise InputError(f"downscale must be > 0, got {downscale}")
    return max(1, int(round(width / downscale))), max(1, int(round(height / downscale)))


def find_object_files(root: os.PathLike | str, stem: str, subdir: str = "masks") -> dict[str, Path]:
    """``root/<subdir>/<object>/<stem>.<ext>`` for every object folder that has one.

    A missing file means "no annotation for this view" (docs/data_formats.md).
    """
    base = Path(root) / subdir
    out: dict[str, Path] = {}
    if base.is_dir():
        for obj in sorted(p for p in base.iterdir() if p.is_dir()):
            f = _find_stem(obj, stem)
            if f is not None:
                out[obj.name] = f
    return out


def load_object_masks(
    root: os.PathLike | str,
    stem: str,
    size: tuple[int, int],
    native_size: Optional[tuple[int, int]] = None,
) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
    """Masks ``root/masks/<object>/<stem>.*`` and coverage maps ``root/coverage/...``.

    Args:
        root: scene folder.
        stem: image stem.
        size: (width, height) of the training image.
        native_size: (width, height) of the source image before downscaling; masks may
            have either size.

    Returns:
        (object → [H, W] bool mask, object → [H, W] float32 coverage).
    """
    sizes = [size] + ([native_size] if native_size else [])
    masks = {
        name: resize_mask(read_mask_array(f, sizes), size)[0]
        for name, f in find_object_files(root, stem, "masks").items()
    }
    coverage = {}
    for name, f in find_object_files(root, stem, "coverage").items():
        arr = read_image_array(f)[:, :, 0]
        got = (arr.shape[1], arr.shape[0])
        if got not in {tuple(s) for s in sizes}:
            raise DataError(f"coverage map is {got[0]}x{got[1]}, expected {size[0]}x{size[1]}", f)
        coverage[name] = torch.from_numpy(
            np.ascontiguousarray(resize_area(arr[:, :, None], *size)[:, :, 0])
        )
    return masks, coverage


def _find_stem(folder: Path, stem: str) -> Optional[Path]:
    for ext in (".png", ".PNG", ".jpg", ".JPG", ".jpeg", ".tif", ".tiff", ".bmp"):
        p = folder / f"{stem}{ext}"
        if p.is_file():
            return p
    return None
