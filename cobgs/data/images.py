"""Image files as the readers meet them, before any pixel is decoded (torch-free): sizes,
aspect ratios and EXIF orientation.

Every reader of this project takes pixels as they are stored: OpenCV's ``IMREAD_UNCHANGED``
and PIL ignore the EXIF orientation tag, while other tools (OpenCV's colour reads, photo
viewers, possibly the SfM library) apply it. A photo whose tag says "rotate 90°" would then be
upright for one reader and sideways for another, and masks, clicks and poses would disagree
about which way is up. Rather than guess, such images are refused with the fix
(:func:`check_upright`): write the pixels upright and drop the tag (docs/data_formats.md).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable, Optional

from cobgs.errors import DataError

#: EXIF tag 0x0112 values and what they ask a viewer to do (1 = as stored).
ORIENTATIONS = {1: "upright as stored", 2: "mirrored left-right", 3: "rotated 180 degrees",
                4: "mirrored top-bottom", 5: "mirrored and rotated 90 degrees", 6: "rotated 90 degrees clockwise",
                7: "mirrored and rotated 90 degrees", 8: "rotated 90 degrees counter-clockwise"}
_ORIENTATION_TAG = 0x0112
#: How many offending files a message names.
_NAMED = 5


#: The image files the scene readers take.
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".exr", ".webp")


def list_images(folder: os.PathLike | str, extensions: tuple[str, ...] = IMAGE_EXTENSIONS) -> list[Path]:
    """Image files directly inside ``folder`` (by extension, case-insensitive), sorted by name.

    Raises:
        DataError: the folder does not exist.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise DataError("image folder not found", folder)
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in extensions)


def same_aspect(w1: int, h1: int, w2: int, h2: int, tol: float = 0.01) -> bool:
    """Whether two image sizes have the same aspect ratio, up to ``tol`` (relative; a
    downscale's rounding, 1008x756 vs 4032x3024 or 510x382 vs 512x384, passes)."""
    return abs(w1 * h2 - w2 * h1) <= tol * w2 * h1


def probe(path: os.PathLike | str) -> tuple[int, int, int]:
    """``(width, height, EXIF orientation)`` of an image file from its header (1 where the
    file has no orientation tag).

    Raises:
        DataError: not an image PIL can open (naming the file and why).
    """
    from PIL import Image

    try:
        with Image.open(path) as im:
            w, h = im.size
            try:
                tag = im.getexif().get(_ORIENTATION_TAG, 1)
            except Exception:  # noqa: BLE001 - a damaged EXIF block: no usable tag
                tag = 1
    except (OSError, ValueError, Image.DecompressionBombError) as exc:
        raise DataError(f"cannot read it as an image ({exc})", Path(path)) from exc
    return int(w), int(h), int(tag) if isinstance(tag, int) and tag in ORIENTATIONS else 1


def rotated(paths: Iterable[os.PathLike | str]) -> list[tuple[Path, int]]:
    """The files among ``paths`` whose EXIF orientation is not 1 (upright as stored), with it."""
    out = []
    for p in paths:
        tag = probe(p)[2]
        if tag != 1:
            out.append((Path(p), tag))
    return out


def check_upright(paths: Iterable[os.PathLike | str], what: str = "image") -> None:
    """Refuse images whose EXIF orientation asks for a rotation or a mirror (module docstring).

    Raises:
        DataError: naming the files, what their tag asks for, and the fix.
    """
    bad = rotated(paths)
    if not bad:
        return
    shown = ", ".join(f"{p.name} ({t}: {ORIENTATIONS[t]})" for p, t in bad[:_NAMED])
    more = f" and {len(bad) - _NAMED} more" if len(bad) > _NAMED else ""
    raise DataError(f"{len(bad)} {what}(s) carry an EXIF orientation other than 1: {shown}{more}. cobgs reads "
                    "pixels as stored, so SfM, masks and clicks would disagree on which way is up; write the "
                    "pixels upright and drop the tag first (e.g. `exiftran -ai *.jpg`, or ImageMagick's "
                    "`mogrify -auto-orient *.jpg`), then make masks and clicks on the upright images",
                    bad[0][0].parent)


def orientation_note(path: Optional[os.PathLike | str]) -> str:
    """" (EXIF orientation 6: rotated 90 degrees clockwise)" for a rotated file, else ""."""
    if path is None:
        return ""
    try:
        tag = probe(path)[2]
    except DataError:
        return ""
    return f" (EXIF orientation {tag}: {ORIENTATIONS[tag]})" if tag != 1 else ""
