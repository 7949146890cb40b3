"""SPIn-NeRF's multiview segmentation annotations (docs/method.md §5, "SPIn-NeRF").

The release (``Multiview-Segmentation-Data.zip``) unpacks to one folder per scene, named as
published, each holding, per annotated view ``<name>``:

    <name>.png           the ground-truth object mask (grey, 0 / 255)
    <name>_pseudo.png    a visualisation (not read)
    <name>_cutout.png    the object cut out of the RGB (not read: it would leak the GT)

plus ``annotations.json`` per scene, a README beside the folders and, from macOS, a
``__MACOSX/`` tree of AppleDouble files (ignored). The RGB and cameras are each scene's own
published data (nerf_llff_data, nerf_real_360, Tanks and Temples, the real lego).

How a mask names its view, as the peers' loaders read it (SA3D ``lib/load_spin.py``, LUDVIG
``utils/data.py``), pinned to one rule per scene so that nothing is guessed:

  index   ``imageNNN``: the NNN-th view of the scene's views sorted by name (the name the
          nerf_llff_data copy gives its downscaled images). Sparse indices stay sparse
          (orchids has ``image015`` after ``image013``: view 14 is not annotated).
  stem    the view's own name (``DJI_20200226_143850_006``), exactly.
  prefix  the view's own name, else that name after removing one ``0_`` / ``1_`` split
          prefix; both matching, or neither, is refused.

The prompt view is the first annotated view by name (SA3D takes the first annotation in
directory order, which is unordered; LUDVIG sorts: we pin LUDVIG's rule). Every other
annotated view is scored.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

from cobgs.errors import DataError, InputError

#: scene -> (published folder name, mask count in the release, naming rule). fork's RGB is not
#: public: its annotations read, its scene cannot be run.
SPIN_SCENES: dict[str, tuple[str, int, str]] = {
    "orchids": ("orchids (llff)", 24, "index"),
    "leaves": ("leaves (llff)", 26, "index"),
    "fern": ("fern (llff)", 20, "index"),
    "room": ("room (llff)", 41, "stem"),
    "horns": ("horns (llff)", 62, "stem"),
    "fortress": ("fortress (llff)", 42, "index"),
    "fork": ("fork (nerf_supervision)", 38, "stem"),
    "pinecone": ("pinecone (nerf_real_360)", 99, "stem"),
    "truck": ("Truck (Tanks & Temples)", 65, "prefix"),
    "lego": ("lego_real_night_radial", 44, "prefix"),
}

#: The files a scene folder may hold beside the GT masks.
_COMPANIONS = ("_pseudo", "_cutout")
_INDEX = re.compile(r"image(\d+)")
_PREFIX = re.compile(r"[01]_(.+)")


@dataclass(frozen=True)
class SpinScene:
    """One scene's annotations, mapped to its views.

    Attributes:
        scene: the scene's key in :data:`SPIN_SCENES`.
        folder: its annotation folder.
        rule: how mask names name views (index, stem or prefix).
        masks: view name -> its GT mask file, in view-name order.
        prompt: the view whose mask prompts (the first annotated view by name).
        scored: the other annotated views, by name.
        mask_names: view name -> the annotation's own file name (for messages and the report).
    """

    scene: str
    folder: Path
    rule: str
    masks: dict
    prompt: str
    scored: tuple
    mask_names: dict

    def to_json(self) -> dict:
        return {"scene": self.scene, "folder": os.fspath(self.folder), "rule": self.rule,
                "masks": {v: os.fspath(p) for v, p in self.masks.items()}, "prompt": self.prompt,
                "scored": list(self.scored), "mask_names": dict(self.mask_names)}


def scene_folder(labels: os.PathLike | str, scene: str) -> Path:
    """The annotation folder of ``scene``: ``labels`` may be the folder holding the scene folders
    (the unpacked release, or a folder holding only that) or the scene's folder itself.

    Raises:
        InputError: an unknown scene (the known ones named).
        DataError: no folder of that name (the folders found named).
    """
    if scene not in SPIN_SCENES:
        raise InputError(f"SPIn-NeRF scene must be one of {list(SPIN_SCENES)}, got {scene!r}")
    root = Path(labels)
    name = SPIN_SCENES[scene][0]
    if not root.is_dir():
        raise DataError("SPIn-NeRF annotation folder not found", root)
    if root.name == name:
        return root
    for cand in (root / name, root / "Multiview-Segmentation-Data" / name):
        if cand.is_dir():
            return cand
    have = sorted(p.name for p in root.iterdir() if p.is_dir() and p.name != "__MACOSX")
    raise DataError(f"no folder {name!r} for SPIn-NeRF scene {scene!r} (an incomplete download? the "
                    f"release has {[v[0] for v in SPIN_SCENES.values()]}; found {have})", root)


def annotation_files(folder: Path) -> dict:
    """name stem -> GT mask file of a scene folder, every other file checked.

    Raises:
        DataError: a file the release does not hold (named), a companion without its mask.
    """
    masks, companions = {}, []
    for p in sorted(folder.iterdir()):
        if p.name.startswith(".") or p.name == "__MACOSX":
            continue  # (hidden files, AppleDouble trees)
        if p.is_file() and p.name == "annotations.json":
            continue
        if not p.is_file() or p.suffix.lower() != ".png":
            raise DataError(f"not a file of the SPIn-NeRF release (a scene folder holds <name>.png, "
                            f"<name>_pseudo.png, <name>_cutout.png and annotations.json)", p)
        comp = next((c for c in _COMPANIONS if p.stem.endswith(c)), None)
        if comp:
            companions.append((p, p.stem[: -len(comp)]))
        else:
            masks[p.stem] = p
    for p, stem in companions:
        if stem not in masks:
            raise DataError(f"{p.name} has no GT mask {stem}.png beside it (a renamed or missing mask?)", p)
    return masks


def _match(rule: str, stem: str, views: list, path: Path) -> str:
    """The view a mask called ``stem`` annotates (see the module docstring)."""
    if rule == "index":
        m = _INDEX.fullmatch(stem)
        if m is None:
            raise DataError(f"mask name {stem!r} is not imageNNN (this scene's masks name views by their "
                            f"index in the sorted view list)", path)
        i = int(m.group(1))
        if i >= len(views):
            raise DataError(f"mask {stem!r} names view index {i}, but the scene has {len(views)} views "
                            f"({views[0]} ... {views[-1]})", path)
        return views[i]
    names = set(views)
    exact = stem if stem in names else None
    stripped = None
    if rule == "prefix":
        m = _PREFIX.fullmatch(stem)
        stripped = m.group(1) if m and m.group(1) in names else None
    if exact and stripped:
        raise DataError(f"mask {stem!r} names two views, {exact!r} and {stripped!r} (with and without its "
                        "split prefix): ambiguous", path)
    found = exact or stripped
    if found is None:
        how = "exactly" + (" or after removing one 0_ / 1_ split prefix" if rule == "prefix" else "")
        raise DataError(f"mask {stem!r} names no view of the scene ({how}; views: {views[:3]} ...); "
                        "a renamed mask, or the RGB of another copy of the scene?", path)
    return found


def image_size(path: Path) -> tuple:
    """(height, width) of an image file from its header (:func:`cobgs.data.images.probe`)."""
    from cobgs.data.images import probe

    w, h, _ = probe(path)
    return h, w


def check_size(path: Path, mask_hw: tuple, view_hw: tuple) -> None:
    """A mask's size against its view's image: the same aspect, within one pixel at the mask's
    scale (the published Truck masks are 980x546 over 979x546 RGB).

    Raises:
        DataError: another size (both named).
    """
    (mh, mw), (vh, vw) = mask_hw, view_hw
    s = mh / vh
    if abs(mw - vw * s) > 1.0 + 1e-9 or mh <= 0:
        raise DataError(f"mask is {mw}x{mh}, its view's image is {vw}x{vh}: not the same picture at any "
                        "scale (a mask of another view or another crop?)", path)


def read_spin_scene(labels: os.PathLike | str, scene: str, views: list,
                    view_size: Optional[Callable[[str], tuple]] = None, check_count: bool = True) -> SpinScene:
    """Read and check one scene's annotations against its views.

    Args:
        labels: the release folder (or the scene's folder).
        scene: a key of :data:`SPIN_SCENES`.
        views: the scene's view names (any order; sorted here).
        view_size: view name -> (height, width) of its image, to check each mask's size.
        check_count: refuse a folder whose mask count is not the release's.

    Raises:
        DataError: a missing folder, an extra or renamed file, a mask naming no view or two, two
            masks naming one view, a mask of the wrong size, a count other than the release's.
    """
    folder = scene_folder(labels, scene)
    _, count, rule = SPIN_SCENES[scene]
    files = annotation_files(folder)
    if not files:
        raise DataError("no GT mask (<name>.png) in the scene folder", folder)
    ordered = sorted(views)
    masks, names = {}, {}
    for stem, path in sorted(files.items()):
        v = _match(rule, stem, ordered, path)
        if v in masks:
            raise DataError(f"masks {names[v]!r} and {path.name!r} both name view {v!r}", path)
        if view_size is not None:
            check_size(path, image_size(path), view_size(v))
        masks[v], names[v] = path, path.name
    if check_count and len(files) != count:  # (after the names: a stray file is named above)
        raise DataError(f"{len(files)} GT masks, the release has {count} for {scene!r} (an incomplete or "
                        "mixed download?)", folder)
    masks = dict(sorted(masks.items()))
    names = {v: names[v] for v in masks}
    # the prompt: the first annotation by its own name (LUDVIG sorts the names; by index for imageNNN)
    prompt = min(masks, key=lambda v: names[v])
    return SpinScene(scene=scene, folder=folder, rule=rule, masks=masks, prompt=prompt,
                     scored=tuple(v for v in masks if v != prompt), mask_names=names)


__all__ = ["SPIN_SCENES", "SpinScene", "scene_folder", "annotation_files", "read_spin_scene", "check_size"]
