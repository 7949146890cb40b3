"""Click prompts (positive / negative points per object and frame) read from a JSON file.

Two layouts are read; :func:`read_clicks` tells them apart and checks every number.

**SAGA-v2 input points** (the community's NVOS click file, e.g. openvdb/fvdb-examples
``instance_segmentation/garfvdb/evaluation/saga_v2_input_points.json``)::

    {"_comment": "...", "_scale": 4,
     "fern": [[533, 367]],
     "horns_center": [[450, 300], [480, 500]], ...}

Keys starting with ``_`` are metadata; every other key is a scene or NVOS task holding
positive clicks ``[x, y]`` on that task's **reference view**. A click's pixel is
``value x _scale`` (default 1) in the reference image's full resolution (the labels'
``reference_image/<task>/<ref>.JPG``, 4032x3024 on LLFF): for the NVOS keys the published
file stores quarter-resolution values (1008x756 frames) with ``_scale = 4``; its other keys
are in their own scenes' frames. A key is looked up as the community's
evaluation does: exactly, then without an ``_undistort`` suffix, then by the name before
the first ``_`` (``horns_center`` -> ``horns``).

**Per-object clicks** (this project's layout, for any scene)::

    {"objects": {
        "mug": {
          "image_size": [4032, 3024],            # optional: the pixel frame of the clicks
          "frames": {
            "IMG_0001": {"positive": [[1510, 980], [1600, 1100]], "negative": [[200, 300]]},
            "IMG_0040": {"positive": [[1400, 1000]]}}}},
     "image_size": [4032, 3024]}                 # optional: the default for every object

A frame is a view name (or its image file's stem); clicks are pixel coordinates ``x`` right,
``y`` down, in the frame ``image_size`` names (default: the view's image file as the
dataset reads it). Every prompted frame becomes a SAM2 conditioning frame. An ``image_size``
of another aspect ratio than the view's image is refused (clicks are never stretched axis by
axis: a portrait size for a landscape photo is a mistake, typically an EXIF rotation).

Checks, all naming the file, the object (or SAGA-v2 entry) and the frame: the file is a
regular file of at most :data:`MAX_FILE_BYTES`, valid JSON without duplicate keys or deep
nesting; every coordinate a finite number in ``[0, MAX_SIDE)`` and inside ``image_size``
(``0 <= x < width``); :func:`match_frames` names a held-out view, a frame given with its file
extension, or a misspelt one (with the closest view names).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from cobgs.data.images import same_aspect
from cobgs.errors import InputError

SAGA = "saga_v2"
OWN = "objects"
#: Largest click file read (a click file is a few KiB; a 55 MB one took 37 s to parse).
MAX_FILE_BYTES = 16 << 20
#: Largest image side and click coordinate accepted, in pixels.
MAX_SIDE = 1 << 20


@dataclass(frozen=True)
class FrameClicks:
    """Clicks on one frame.

    Attributes:
        frame: the frame as the file names it ("" for a SAGA-v2 entry: the NVOS reference
            view).
        points: float64 [n, 2] (x, y) in the object's pixel frame.
        labels: int [n], 1 = positive, 0 = negative.
    """

    frame: str
    points: np.ndarray
    labels: np.ndarray

    @property
    def num_positive(self) -> int:
        return int((self.labels == 1).sum())


@dataclass(frozen=True)
class ObjectClicks:
    """One object's clicks.

    Attributes:
        key: the file's key for it.
        frames: its prompted frames, in file order.
        image_size: (width, height) of the pixel frame the clicks are in; None = each
            frame's own image (per-object layout) or the reference image's full
            resolution (SAGA-v2).
        layout: :data:`SAGA` or :data:`OWN`.
    """

    key: str
    frames: tuple[FrameClicks, ...]
    image_size: Optional[tuple[int, int]] = None
    layout: str = OWN


@dataclass(frozen=True)
class ClickFile:
    """A checked click file: its layout, objects and (SAGA-v2) scale."""

    path: Path
    layout: str
    objects: dict[str, ObjectClicks] = field(default_factory=dict)
    scale: float = 1.0

    def lookup(self, names: Sequence[str]) -> ObjectClicks:
        """The entry of the first of ``names`` the file has. The per-object layout matches
        names exactly; SAGA-v2 keys also match without ``_undistort`` and by the name before
        the first ``_``, as the community's NVOS evaluation looks them up.

        Raises:
            InputError: none matches (the file and its keys are named).
        """
        names = [n for n in dict.fromkeys(names) if n]
        for n in names:
            if n in self.objects:
                return self.objects[n]
        if self.layout == SAGA:
            for n in names:
                for cand in (n.replace("_undistort", ""), n.split("_")[0]):
                    if cand in self.objects:
                        return self.objects[cand]
        what = "entry" if self.layout == SAGA else "object"
        raise InputError(f"click file {self.path}: no {what} for {' / '.join(repr(n) for n in names)} "
                         f"({what} keys in the file: {sorted(self.objects)[:12]})")


def _bad(path: Path, where: str, what: str) -> InputError:
    return InputError(f"click file {path}: {where}: {what}")


def _coordinate(c) -> bool:
    """A pixel coordinate: a finite number in [0, MAX_SIDE) (an int is compared before any
    conversion: 10**400 has no float)."""
    if isinstance(c, bool) or not isinstance(c, (int, float)):
        return False
    if isinstance(c, int):
        return 0 <= c < MAX_SIDE
    return math.isfinite(c) and 0 <= c < MAX_SIDE


def _points(path: Path, where: str, value, kind: str) -> np.ndarray:
    if not isinstance(value, list):
        raise _bad(path, where, f"{kind} must be a list of [x, y] pairs, got {type(value).__name__}")
    out = []
    for i, p in enumerate(value):
        if (not isinstance(p, list) or len(p) != 2
                or not all(isinstance(c, (int, float)) and not isinstance(c, bool) for c in p)):
            raise _bad(path, where, f"{kind} point {i} must be [x, y] (two numbers), got {_short(p)}")
        if not all(_coordinate(c) for c in p):
            raise _bad(path, where, f"{kind} point {i} must be two finite pixel coordinates in [0, {MAX_SIDE}), "
                                    f"got {_short(p)}")
        out.append([float(p[0]), float(p[1])])
    return np.asarray(out, np.float64).reshape(-1, 2)


def _short(value, limit: int = 60) -> str:
    text = repr(value) if not (isinstance(value, int) and abs(value) >= 10 ** 30) else f"<{len(str(value))}-digit integer>"
    if isinstance(value, list):
        text = "[" + ", ".join(_short(v, limit) for v in value[:4]) + (", ..." if len(value) > 4 else "") + "]"
    return text if len(text) <= limit else text[:limit - 4] + " ..."


def _size(path: Path, where: str, value) -> Optional[tuple[int, int]]:
    if value is None:
        return None
    if (not isinstance(value, list) or len(value) != 2
            or not all(isinstance(c, int) and not isinstance(c, bool) and 0 < c <= MAX_SIDE for c in value)):
        raise _bad(path, where, f"image_size must be [width, height] (two integers in 1..{MAX_SIDE}), "
                                f"got {_short(value)}")
    return int(value[0]), int(value[1])


def _read_saga(path: Path, data: dict) -> ClickFile:
    scale = data.get("_scale", 1)
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not (0 < scale <= 1024) \
            or (isinstance(scale, float) and not math.isfinite(scale)):
        raise _bad(path, "_scale", f"must be a number in (0, 1024], got {_short(scale)}")
    objects = {}
    for key, value in data.items():
        if key.startswith("_"):
            continue
        pts = _points(path, f"entry {key!r}", value, "clicks")
        if not len(pts):
            raise _bad(path, f"entry {key!r}", "no click")
        pts = pts * float(scale)
        objects[key] = ObjectClicks(key, (FrameClicks("", pts, np.ones(len(pts), np.int64)),), None, SAGA)
    if not objects:
        raise _bad(path, "top level", "no entry (expected scene or task names with [[x, y], ...] clicks)")
    return ClickFile(path, SAGA, objects, float(scale))


def _read_own(path: Path, data: dict) -> ClickFile:
    unknown = sorted(set(data) - {"objects", "image_size", "format", "_comment"})
    if unknown:
        raise _bad(path, "top level", f"unknown key(s) {unknown} (expected objects, image_size)")
    default_size = _size(path, "top level", data.get("image_size"))
    objs = data["objects"]
    if not isinstance(objs, dict) or not objs:
        raise _bad(path, "objects", "must map object names to {\"frames\": {...}}")
    objects = {}
    for name, entry in objs.items():
        where = f"object {name!r}"
        if not isinstance(entry, dict) or "frames" not in entry:
            raise _bad(path, where, "must be {\"frames\": {FRAME: {\"positive\": [[x, y], ...], "
                                    "\"negative\": [...]}}}")
        extra = sorted(set(entry) - {"frames", "image_size"})
        if extra:
            raise _bad(path, where, f"unknown key(s) {extra} (expected frames, image_size)")
        size = _size(path, where, entry.get("image_size")) or default_size
        frames_in = entry["frames"]
        if not isinstance(frames_in, dict) or not frames_in:
            raise _bad(path, where, "frames must map frame names to clicks and name at least one")
        frames = []
        for frame, clicks in frames_in.items():
            fwhere = f"object {name!r}, frame {frame!r}"
            if not isinstance(clicks, dict):
                raise _bad(path, fwhere, "must be {\"positive\": [[x, y], ...], \"negative\": [[x, y], ...]}")
            bad_keys = sorted(set(clicks) - {"positive", "negative"})
            if bad_keys:
                raise _bad(path, fwhere, f"unknown key(s) {bad_keys} (expected positive, negative)")
            pos = _points(path, fwhere, clicks.get("positive", []), "positive")
            neg = _points(path, fwhere, clicks.get("negative", []), "negative")
            if not len(pos):
                raise _bad(path, fwhere, "needs at least one positive click (SAM2 would find nothing)")
            if size is not None:
                for kind, pts in (("positive", pos), ("negative", neg)):
                    out = [p for p in pts.tolist() if p[0] >= size[0] or p[1] >= size[1]]
                    if out:
                        raise _bad(path, fwhere, f"{kind} click {out[0]} lies outside image_size "
                                                 f"{list(size)} (pixels 0 <= x < width, 0 <= y < height)")
            frames.append(FrameClicks(str(frame), np.concatenate([pos, neg]),
                                      np.concatenate([np.ones(len(pos), np.int64), np.zeros(len(neg), np.int64)])))
        objects[str(name)] = ObjectClicks(str(name), tuple(frames), size, OWN)
    return ClickFile(path, OWN, objects)


class _Duplicate(ValueError):
    pass


def _no_duplicates(pairs: list) -> dict:
    seen: dict = {}
    for k, v in pairs:
        if k in seen:
            raise _Duplicate(k)
        seen[k] = v
    return seen


def read_clicks(path: os.PathLike | str) -> ClickFile:
    """Read and check a click file (module docstring: both layouts).

    Raises:
        InputError: the file is missing, is no regular file, is larger than
            :data:`MAX_FILE_BYTES`, is not JSON, repeats a key, or a value is malformed: the
            message names the file, the object (or entry) and the frame.
    """
    p = Path(path)
    if not p.exists():
        raise InputError(f"click file {p} does not exist")
    if p.is_dir():
        raise InputError(f"click file {p} is a folder; masks.points_file names the JSON file itself")
    if not p.is_file():
        raise InputError(f"click file {p} is not a regular file (a pipe or a device?); give a JSON file")
    size = p.stat().st_size
    if size > MAX_FILE_BYTES:
        raise InputError(f"click file {p} is {size / 2**20:.1f} MiB, more than the {MAX_FILE_BYTES >> 20} MiB a "
                         "click file may have (it holds a few clicks per object and frame)")
    try:
        data = json.loads(p.read_text(encoding="utf-8-sig"), object_pairs_hook=_no_duplicates)
    except _Duplicate as exc:
        raise InputError(f"click file {p}: key {exc.args[0]!r} appears twice in one JSON object (JSON keeps only "
                         "the last: merge the two)") from None
    except RecursionError:
        raise InputError(f"click file {p}: not a click file (JSON nested too deep to read)") from None
    except (UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"click file {p}: not valid JSON ({exc})") from exc
    if not isinstance(data, dict):
        raise InputError(f"click file {p}: expected a JSON object at the top, got {type(data).__name__}")
    if "objects" in data:
        return _read_own(p, data)
    return _read_saga(p, data)


def to_image_pixels(points: np.ndarray, frame_size: Optional[tuple[int, int]],
                    image_size: tuple[int, int]) -> np.ndarray:
    """Clicks from their pixel frame ``frame_size`` (w, h; None = already the image's) to
    an image of ``image_size`` (w, h) of the same aspect (:func:`check_frame_size`)."""
    if frame_size is None:
        return np.asarray(points, np.float64)
    sx = image_size[0] / frame_size[0]
    sy = image_size[1] / frame_size[1]
    return np.asarray(points, np.float64) * np.array([sx, sy])


def locate(file: ClickFile | Path, entry: ObjectClicks, frame: Optional[str] = None) -> str:
    """"click file F, object 'mug', frame 'IMG_1'" (SAGA-v2: "entry 'fern'") for messages."""
    path = file.path if isinstance(file, ClickFile) else file
    text = f"click file {path}, {'entry' if entry.layout == SAGA else 'object'} {entry.key!r}"
    return text + (f", frame {frame!r}" if frame is not None else "")


def check_frame_size(file: ClickFile | Path, entry: ObjectClicks, frame: str, frame_size: Optional[tuple[int, int]],
                     image_size: tuple[int, int], image: os.PathLike | str) -> None:
    """Refuse clicks whose pixel frame has another aspect than the image they are for:
    scaling them axis by axis would move them (a portrait ``image_size`` for a landscape
    view, typically a photo whose EXIF orientation one tool applied and another did not).

    Raises:
        InputError: naming file, object, frame and both sizes.
    """
    if frame_size is None or same_aspect(frame_size[0], frame_size[1], image_size[0], image_size[1]):
        return
    raise InputError(f"{locate(file, entry, frame)}: the clicks are in a {frame_size[0]}x{frame_size[1]} frame, but "
                     f"the view's image {image} is {image_size[0]}x{image_size[1]}: another aspect ratio (rotated, "
                     "cropped or another view's size?); clicks are scaled to the image only when the aspect "
                     "matches: give image_size as the image's own size")


def match_frames(file: ClickFile, entry: ObjectClicks, views: Sequence[tuple[str, str]],
                 held_out: Sequence[tuple[str, str]] = ()) -> list[int]:
    """The training view each frame of a per-object entry names, as indices into ``views``.

    Args:
        file: the click file (for messages).
        entry: its entry for one object.
        views: the training views as ``(name, image file name)``.
        held_out: the held-out views, the same way.

    Raises:
        InputError: a frame names a held-out view (by name or image stem), names a view with
            its file extension, or names none (the closest view names are given).
    """
    import difflib

    by_name = {n: i for i, (n, _) in enumerate(views)}
    by_stem = {Path(f).stem: i for i, (_, f) in enumerate(views) if f}
    held = {n for n, _ in held_out} | {Path(f).stem for _, f in held_out if f}
    out = []
    for fc in entry.frames:
        frame = fc.frame
        if frame in by_name:
            out.append(by_name[frame])
            continue
        if frame in by_stem:
            out.append(by_stem[frame])
            continue
        w = locate(file, entry, frame)
        if frame in held:
            raise InputError(f"{w}: a held-out view; clicks must be on training views (held-out views are "
                             "kept for the evaluation)")
        stem = Path(frame).stem
        if stem != frame and (stem in by_name or stem in by_stem):
            raise InputError(f"{w}: frames are named without the file extension: {stem!r}")
        if stem != frame and stem in held:
            raise InputError(f"{w}: a held-out view (and frames are named without the file extension)")
        close = difflib.get_close_matches(frame, list(by_name), n=3, cutoff=0.6)
        hint = f"; did you mean {' or '.join(repr(c) for c in close)}?" if close else \
            f" (training views like {list(by_name)[:4]})"
        raise InputError(f"{w}: no training view of that name{hint}")
    return out


__all__ = ["ClickFile", "FrameClicks", "MAX_FILE_BYTES", "MAX_SIDE", "ObjectClicks", "OWN", "SAGA",
           "check_frame_size", "match_frames", "locate", "read_clicks", "same_aspect", "to_image_pixels"]


def interior_clicks(mask: np.ndarray, count: int) -> np.ndarray:
    """``count`` positive clicks inside a binary mask, [count, 2] float (x, y) pixel centres,
    deterministic: the first at the pixel farthest from the mask's edge (of equals, the one
    nearest the mask's centroid), each next one at the pixel whose smaller distance, to the
    edge or to the clicks so far, is largest (of equals, the farthest from the clicks): spread
    over the object, never on its boundary. Fewer when the mask has fewer pixels.

    Raises:
        InputError: an empty mask.
    """
    import cv2

    m = np.ascontiguousarray(np.asarray(mask, bool))
    if not m.any():
        raise InputError("cannot place clicks in an empty mask")
    edge = cv2.distanceTransform(np.pad(m, 1).astype(np.uint8), cv2.DIST_L2, 5)[1:-1, 1:-1].astype(np.float64)
    ys, xs = np.mgrid[0:m.shape[0], 0:m.shape[1]]
    cy, cx = np.argwhere(m).mean(0)
    score = edge - 1e-3 * np.hypot(xs - cx, ys - cy)  # (ties on a plateau: the one nearest the centroid)
    near = np.full(m.shape, np.inf)
    out = []
    for _ in range(min(int(count), int(m.sum()))):
        score[~m] = -np.inf
        y, x = np.unravel_index(int(np.argmax(score)), score.shape)
        out.append((float(x), float(y)))
        near = np.minimum(near, np.hypot(xs - x, ys - y))
        score = np.minimum(edge, near) + 1e-3 * near  # (ties: the one farthest from the clicks so far)
    return np.asarray(out, np.float32).reshape(-1, 2)
