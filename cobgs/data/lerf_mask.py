"""The LERF-mask benchmark (Gaussian Grouping's annotations of LERF scenes), docs/method.md §5.

Published layout of a scene folder::

    <scene>/images/<name>.jpg                 every view
    <scene>/images_train/<name>.jpg           the training views (a subset of images/)
    <scene>/sparse/0/                         COLMAP model of every view
    <scene>/test_mask/<idx>/<prompt>.png      GT of prompt <prompt> in test view <idx>

Training views are the names in ``images_train/``; test views are all other images,
sorted by name, and ``<idx>`` is a view's position in that sorted list (``0``, ``1``,
...; zero-padded folder names are accepted). Some test views have no GT folder (left out
and listed, :func:`read_lerf_gt`), and some GT masks are empty: those are scored as
Gaussian Grouping's script scores them (:func:`cobgs.evaluate.protocols.lerf_prompt_scores`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from cobgs.errors import DataError

#: The published prompts of each scene.
LERF_PROMPTS: dict[str, tuple[str, ...]] = {
    "figurines": ("green apple", "green toy chair", "old camera", "porcelain hand", "red apple",
                  "red toy chair", "rubber duck with red hat"),
    "ramen": ("chopsticks", "egg", "glass of water", "pork belly", "wavy noodles in bowl",
              "yellow bowl"),
    "teatime": ("apple", "bag of cookies", "coffee mug", "cookies on a plate", "paper napkin",
                "plate", "sheep", "spoon handle", "stuffed bear", "tea in a glass"),
}

_IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")


def _image_stems(folder: Path) -> list[str]:
    return sorted(p.stem for p in folder.iterdir() if p.is_file() and p.suffix.lower() in _IMAGE_SUFFIXES)


def lerf_split(scene_dir: os.PathLike | str) -> tuple[list[str], list[str]]:
    """(train stems, test stems), each sorted by name.

    Raises:
        DataError: ``images/`` or ``images_train/`` is missing, or a training name is not
            among the images.
    """
    root = Path(scene_dir)
    images, train_dir = root / "images", root / "images_train"
    for d in (images, train_dir):
        if not d.is_dir():
            raise DataError(f"LERF-mask scene lacks {d.name}/ (expected images/, images_train/, "
                            "sparse/0/, test_mask/)", d)
    every = _image_stems(images)
    train = _image_stems(train_dir)
    if not train:
        raise DataError("images_train/ holds no image", train_dir)
    unknown = sorted(set(train) - set(every))
    if unknown:
        raise DataError(f"{len(unknown)} training view(s) are not in images/: {unknown[:5]}", train_dir)
    kept = set(train)
    test = [s for s in every if s not in kept]
    if not test:
        raise DataError("every image is a training view; no test view is left", images)
    return train, test


@dataclass
class LerfGroundTruth:
    """The GT masks of one LERF-mask scene.

    Attributes:
        test_views: test view stems in protocol order (index = GT folder name).
        masks: (test view stem, prompt) -> GT mask path.
        prompts: every prompt with at least one GT file, sorted.
        views_without_gt: test views with no ``test_mask/<idx>/`` folder.
        unknown_indices: GT folders whose index is not a test view (reported, unused).
    """

    test_views: list[str]
    masks: dict[tuple[str, str], Path] = field(default_factory=dict)
    prompts: list[str] = field(default_factory=list)
    views_without_gt: list[str] = field(default_factory=list)
    unknown_indices: list[str] = field(default_factory=list)

    def views_for(self, prompt: str) -> list[str]:
        """Test views that have a GT file for ``prompt``, in protocol order."""
        return [v for v in self.test_views if (v, prompt) in self.masks]

    def to_json(self) -> dict:
        return {
            "test_views": list(self.test_views),
            "masks": [{"view": v, "prompt": p, "path": os.fspath(path)}
                      for (v, p), path in sorted(self.masks.items())],
            "prompts": list(self.prompts),
            "views_without_gt": list(self.views_without_gt),
            "unknown_indices": list(self.unknown_indices),
        }


def read_lerf_gt(scene_dir: os.PathLike | str) -> LerfGroundTruth:
    """Index ``test_mask/`` against the sorted test views (see the module docstring).

    Raises:
        DataError: the split cannot be made, ``test_mask/`` is missing or has no PNG.
    """
    root = Path(scene_dir)
    _, test = lerf_split(root)
    gt_root = root / "test_mask"
    if not gt_root.is_dir():
        raise DataError("LERF-mask scene lacks test_mask/ (the GT masks)", gt_root)
    out = LerfGroundTruth(test_views=list(test))
    seen = set()
    for d in sorted(gt_root.iterdir()):
        if not d.is_dir():
            continue
        try:
            idx = int(d.name)
        except ValueError:
            out.unknown_indices.append(d.name)
            continue
        if not 0 <= idx < len(test):
            out.unknown_indices.append(d.name)
            continue
        view = test[idx]
        for f in sorted(d.glob("*.png")):
            out.masks[(view, f.stem)] = f
            seen.add(view)
    if not out.masks:
        raise DataError("test_mask/ holds no <idx>/<prompt>.png mask", gt_root)
    out.prompts = sorted({p for _, p in out.masks})
    out.views_without_gt = [v for v in test if v not in seen]
    return out
