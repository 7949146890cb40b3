"""The posed scene layouts the readers take, behind one registry (standard library only).

A :class:`SceneFormat` is everything the rest of the project needs of a layout: how to
recognise a folder in it (``marker``, standard library only, so ``cobgs new`` stays fast),
its reader (``reader``, a ``module:function`` imported when a scene is read) and the
keywords that reader takes, and what sets the layout apart: it carries its own train / test
split, its images are composited on a background, its alpha channel is an object's mask, it has
no ``images/`` folder for SfM, the scene type it usually is. Layout detection
(:func:`cobgs.data.layout.detect_layout`), :func:`cobgs.data.readers.read_scene`, the dataset
kinds (:data:`cobgs.data.build.KINDS`), the stages and the trainer read these; no format is
special-cased anywhere else.

A new layout is its reader module and one line of :data:`FORMATS` (docs/data_formats.md,
"Adding a dataset format"). The order of :data:`FORMATS` is the detection order: the first
whose marker matches wins.
"""

from __future__ import annotations

import importlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional

from cobgs.errors import DataError

#: The keywords :meth:`SceneFormat.read` may pass a reader (each format names those it takes).
READ_KEYWORDS = ("test_every", "test_names", "background", "distortion")


@dataclass(frozen=True)
class SceneFormat:
    """One posed layout (module docstring).

    Attributes:
        name: the format's (and the dataset kind's) name.
        marker: whether a folder is in this layout.
        found: what ``cobgs new`` says it found.
        reader: ``"module:function"``, called ``(path, downscale=..., **takes)``.
        takes: the keywords of :data:`READ_KEYWORDS` the reader accepts.
        own_split: the data holds its train / test split (no held-out views are chosen).
        composited: its images are RGBA composited on a fixed background (no random
            background in training).
        alpha_object: the object the images' alpha channel is the mask of ("" for none).
        images_folder: it has an ``images/`` folder (``images_<k>/``) SfM can read.
        integer_downscale: the reader takes only whole downscale factors.
        scene_type: "forward" or "360": the scene type it usually is.
    """

    name: str
    marker: Callable[[Path], bool]
    found: str
    reader: str
    takes: tuple[str, ...] = ("test_every", "test_names")
    own_split: bool = False
    composited: bool = False
    alpha_object: str = ""
    images_folder: bool = True
    integer_downscale: bool = False
    scene_type: str = "forward"

    def read(self, path: os.PathLike | str, *, downscale: float = 1.0, **kw: Any):
        """The scene at ``path`` (:class:`cobgs.data.scene.Scene`), with the keywords of
        :data:`READ_KEYWORDS` this reader takes (None values dropped).

        Raises:
            DataError: a keyword this layout cannot honour (held-out views of a layout with its
                own split, a fractional downscale where only whole ones exist).
        """
        unknown = sorted(set(kw) - set(READ_KEYWORDS))
        if unknown:
            raise TypeError(f"unknown keyword(s) {unknown}; expected some of {list(READ_KEYWORDS)}")
        given = {k: v for k, v in kw.items() if v is not None}
        if self.own_split and given.get("test_names") is not None:
            raise DataError(f"{self.name} scenes carry their own test split; test_names is not supported", path)
        if self.integer_downscale:
            k = int(round(downscale))
            if abs(downscale - k) > 1e-9:
                raise DataError(f"{self.name} downscale must be an integer, got {downscale}", path)
            downscale = k
        module, _, func = self.reader.partition(":")
        fn = getattr(importlib.import_module(module), func)
        return fn(path, downscale=downscale, **{k: v for k, v in given.items() if k in self.takes})


def colmap_model_dir(root: os.PathLike | str) -> Optional[Path]:
    """The folder holding a complete COLMAP model under ``root`` (``sparse/0``, ``sparse`` or
    the folder itself; ``.bin`` or ``.txt``), or None."""
    root = Path(root)
    for cand in (root / "sparse" / "0", root / "sparse", root):
        for ext in (".bin", ".txt"):
            if all((cand / f"{n}{ext}").is_file() for n in COLMAP_MODEL_FILES):
                return cand
    return None


COLMAP_MODEL_FILES = ("cameras", "images", "points3D")

#: Every posed layout, in detection order (module docstring).
FORMATS: dict[str, SceneFormat] = {f.name: f for f in (
    SceneFormat("blender", lambda r: (r / "transforms_train.json").is_file(),
                "transforms_train.json (NeRF-synthetic layout) found; its posed views are triangulated for the "
                "initial points", "cobgs.data.blender:read_blender", takes=("background",), own_split=True,
                composited=True, alpha_object="object", images_folder=False, scene_type="360"),
    SceneFormat("transforms", lambda r: (r / "transforms.json").is_file(),
                "transforms.json (NeRF / nerfstudio cameras) found", "cobgs.data.transforms:read_transforms",
                takes=("test_every", "test_names", "background")),
    SceneFormat("colmap", lambda r: colmap_model_dir(r) is not None,
                "a COLMAP model (sparse/0) found: its cameras and points are used", "cobgs.data.colmap:read_colmap",
                takes=("test_every", "test_names", "distortion")),
    SceneFormat("llff", lambda r: (r / "poses_bounds.npy").is_file(),
                "poses_bounds.npy (LLFF poses) found; points come from triangulation", "cobgs.data.llff:read_llff",
                integer_downscale=True),
)}


def scene_format(name: str, path: Optional[os.PathLike | str] = None) -> SceneFormat:
    """The layout called ``name``.

    Raises:
        DataError: no such layout (the known ones named).
    """
    if name not in FORMATS:
        raise DataError(f"unknown scene format {name!r} (expected one of {', '.join(FORMATS)})", path)
    return FORMATS[name]


def detect(root: os.PathLike | str) -> Optional[str]:
    """The first layout of :data:`FORMATS` whose marker matches ``root``, or None."""
    root = Path(root)
    return next((f.name for f in FORMATS.values() if f.marker(root)), None)


def layouts_expected() -> str:
    """What the layouts look like, for a message: "transforms_train.json, transforms.json, ..."."""
    return ", ".join(f.found.split(" found")[0] for f in FORMATS.values())


__all__ = ["FORMATS", "READ_KEYWORDS", "SceneFormat", "colmap_model_dir", "detect", "layouts_expected", "scene_format"]
