"""The NVOS benchmark's label archive (docs/method.md §5): tasks, held-out target, scribbles, GT.

Published layout of the labels folder (one sub-folder per task)::

    <labels>/masks/<task>/<target>.JPG          the held-out target view (full resolution)
    <labels>/masks/<task>/<target>_mask.png     its ground-truth mask (full resolution)
    <labels>/reference_image/<task>/<ref>.JPG   the view the scribbles were drawn on
    <labels>/scribbles/<task>/pos_*.png         positive scribbles (1/4 resolution; any
    <labels>/scribbles/<task>/neg_*.png         negative scribbles   name holding pos / neg)

The images themselves are the LLFF scenes; two tasks share the ``horns`` scene. The
target view must be held out of training; the reference view is a training view that the
scribbles prompt. :func:`read_nvos_task` checks every file and names the first missing one.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from cobgs.errors import DataError, InputError

#: task -> (LLFF scene, target view stem, reference view stem), as published.
NVOS_TASKS: dict[str, tuple[str, str, str]] = {
    "fern": ("fern", "IMG_4027", "IMG_4038"),
    "flower": ("flower", "IMG_2962", "IMG_2983"),
    "fortress": ("fortress", "IMG_1800", "IMG_1821"),
    "horns_center": ("horns", "DJI_20200223_163024_597", "DJI_20200223_163055_437"),
    "horns_left": ("horns", "DJI_20200223_163024_597", "DJI_20200223_163055_437"),
    "leaves": ("leaves", "IMG_2997", "IMG_3011"),
    "orchids": ("orchids", "IMG_4480", "IMG_4479"),
    "trex": ("trex", "DJI_20200223_163619_411", "DJI_20200223_163607_906"),
}

_IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")


@dataclass(frozen=True)
class NvosTask:
    """One NVOS task's files.

    Attributes:
        task: task name (a folder under ``masks/``).
        scene: the LLFF scene it uses (``horns`` for both horns tasks).
        target: stem of the held-out target view.
        reference: stem of the reference (scribbled) view.
        gt_mask: the full-resolution ground-truth mask of the target view.
        target_image: the target view as shipped with the labels.
        reference_image: the reference view as shipped with the labels.
        positive_scribbles, negative_scribbles: scribble images, sorted by name.
    """

    task: str
    scene: str
    target: str
    reference: str
    gt_mask: Path
    target_image: Optional[Path]
    reference_image: Optional[Path]
    positive_scribbles: tuple[Path, ...]
    negative_scribbles: tuple[Path, ...]

    def to_json(self) -> dict:
        return {
            "task": self.task, "scene": self.scene, "target": self.target,
            "reference": self.reference, "gt_mask": os.fspath(self.gt_mask),
            "target_image": None if self.target_image is None else os.fspath(self.target_image),
            "reference_image": None if self.reference_image is None else os.fspath(self.reference_image),
            "positive_scribbles": [os.fspath(p) for p in self.positive_scribbles],
            "negative_scribbles": [os.fspath(p) for p in self.negative_scribbles],
        }


def nvos_scene_of(task: str) -> str:
    """The LLFF scene of a task: the published table, else the name before the first ``_``."""
    if task in NVOS_TASKS:
        return NVOS_TASKS[task][0]
    return task.split("_")[0]


def _images_in(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir()
                  if p.is_file() and p.suffix.lower() in _IMAGE_SUFFIXES and not p.stem.endswith("_mask"))


def scribble_files(folder: Path) -> tuple[tuple[Path, ...], tuple[Path, ...]]:
    """The positive and negative scribble images of a task folder, as the reference
    methods match them: names containing ``pos`` / ``neg`` (any case); visualisation
    files (names containing ``vis``) and other images are ignored.

    Raises:
        DataError: a name contains both ``pos`` and ``neg`` (the file is named).
    """
    pos, neg = [], []
    for p in _images_in(folder):
        name = p.stem.lower()
        if "vis" in name:
            continue
        is_pos, is_neg = "pos" in name, "neg" in name
        if is_pos and is_neg:
            raise DataError("scribble file name contains both 'pos' and 'neg': cannot tell "
                            "whether it is a positive or a negative scribble (rename it)", p)
        if is_pos:
            pos.append(p)
        elif is_neg:
            neg.append(p)
    return tuple(pos), tuple(neg)


def labels_root(labels_dir: os.PathLike | str) -> Path:
    """The folder holding ``masks/``, ``reference_image/`` and ``scribbles/``: ``labels_dir``
    itself, or its ``llff/`` sub-folder (the download unpacks to ``labels/llff/``).

    Raises:
        DataError: neither holds ``masks/`` (both places are named).
    """
    root = Path(labels_dir)
    if not root.is_dir():
        raise DataError("NVOS labels folder not found (expected masks/, reference_image/, "
                        "scribbles/ inside, or an llff/ folder holding them)", root)
    if not (root / "masks").is_dir() and (root / "llff" / "masks").is_dir():
        return root / "llff"
    if not (root / "masks").is_dir():
        raise DataError("not an NVOS labels folder: no masks/ in it nor in llff/ (give the folder "
                        "holding masks/, reference_image/ and scribbles/, e.g. labels/llff)", root)
    return root


def read_nvos_task(labels_dir: os.PathLike | str, task: str) -> NvosTask:
    """Locate and check one task's files in an NVOS labels folder.

    ``labels_dir`` may be the folder the download unpacks (``labels/``) or its ``llff/``
    sub-folder (:func:`labels_root`). The target is the image in ``masks/<task>/`` (its GT is ``<target>_mask.png``); the
    reference is the image in ``reference_image/<task>/``. For the published tasks both
    are cross-checked against :data:`NVOS_TASKS`.

    Raises:
        DataError: a folder or file is missing or ambiguous (the path is named).
    """
    root = labels_root(labels_dir)
    if not task or "/" in task:
        raise InputError(f"NVOS task must be a folder name such as 'fern', got {task!r}")
    mdir = root / "masks" / task
    if not mdir.is_dir():
        known = sorted(p.name for p in (root / "masks").iterdir() if p.is_dir()) \
            if (root / "masks").is_dir() else []
        raise DataError(f"no masks/{task}/ folder for NVOS task {task!r} (tasks found: {known})", mdir)
    masks = sorted(mdir.glob("*_mask.png"))
    if len(masks) != 1:
        raise DataError(f"expected exactly one <target>_mask.png, found {[p.name for p in masks]}", mdir)
    gt = masks[0]
    target = gt.name[: -len("_mask.png")]
    target_images = [p for p in _images_in(mdir) if p.stem == target]
    table = NVOS_TASKS.get(task)
    if table is not None and table[1] != target:
        raise DataError(f"task {task!r}: GT mask is for {target!r}, the published target is "
                        f"{table[1]!r}", gt)

    rdir = root / "reference_image" / task
    ref_images = _images_in(rdir) if rdir.is_dir() else []
    if len(ref_images) > 1:
        raise DataError(f"expected one reference image, found {[p.name for p in ref_images]}", rdir)
    if ref_images:
        reference = ref_images[0].stem
    elif table is not None:
        reference = table[2]
    else:
        raise DataError("reference image not found (needed to know which view the scribbles "
                        "were drawn on)", rdir)
    if table is not None and table[2] != reference:
        raise DataError(f"task {task!r}: reference image is {reference!r}, the published "
                        f"reference is {table[2]!r}", rdir)

    sdir = root / "scribbles" / task
    if not sdir.is_dir():
        raise DataError("scribbles folder not found", sdir)
    pos, neg = scribble_files(sdir)
    if not pos:
        raise DataError("no positive scribble found (an image whose name contains 'pos', "
                        "e.g. pos_0.png)", sdir)
    return NvosTask(task=task, scene=nvos_scene_of(task), target=target, reference=reference,
                    gt_mask=gt, target_image=target_images[0] if target_images else None,
                    reference_image=ref_images[0] if ref_images else None,
                    positive_scribbles=pos, negative_scribbles=neg)


def read_gt_mask(path: os.PathLike | str) -> np.ndarray:
    """A ground-truth mask as 8-bit grey [H, W] uint8 (colour masks: their luminance).

    The protocol binarises with ``> 128`` afterwards (:func:`cobgs.evaluate.metrics.binarize`).
    """
    import cv2

    p = Path(path)
    if not p.is_file():
        raise DataError("ground-truth mask not found", p)
    arr = cv2.imread(os.fspath(p), cv2.IMREAD_UNCHANGED)
    if arr is None:
        raise DataError("unreadable mask image", p)
    if arr.dtype == np.uint16:
        arr = (arr >> 8).astype(np.uint8)
    elif arr.dtype != np.uint8:
        raise DataError(f"expected an 8- or 16-bit mask, got {arr.dtype}", p)
    if arr.ndim == 3:
        if arr.shape[2] == 4:
            arr = arr[:, :, :3]
        arr = cv2.cvtColor(arr, cv2.COLOR_BGR2GRAY)
    return np.ascontiguousarray(arr)
