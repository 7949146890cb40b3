"""The per-scene pictures: held-out view, GT, each method's mask, error overlay, boundary
crop, object alone and object removed — composed from cached PNGs with numpy and Pillow.

Nothing here measures anything: the overlay shows the pixels the evaluate stage counted
(the prediction resized NEAREST to the GT's size and both binarised at > 128, exactly as
:func:`cobgs.evaluate.protocols.compare_masks` does), and the numbers printed under a picture are the
evaluate stage's own per-view numbers.

One boundary crop window is chosen per (scene, object, view) and shared by every method,
so that the crops compare like with like: the window where the methods' errors (false
positives + false negatives, summed over methods) are densest; with no error at all, the
window holding most of the GT boundary.
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from .errors import ReportError

FP_RGB = (230, 75, 53)  # false positive: predicted, not in GT
FN_RGB = (77, 187, 213)  # false negative: in GT, missed
CROP_RGB = (255, 221, 0)
# Pictures wider than this are downscaled for the page (the grid shows them ~170 px wide,
# the comparison ~540 px): a LERF-mask workflow has dozens of prompts x methods, and the
# report must stay small enough to mail. Boundary detail lives in the full-resolution crop.
MAX_WIDTH_PX = 480
JPEG_QUALITY = 90  # photographs (held-out view, object alone / removed); masks and overlays stay PNG
CROP_DISPLAY_PX = 240
THRESHOLD_U8 = 128  # as cobgs.evaluate.protocols: "> 128 of 255"


def slug(name: str) -> str:
    """A file-name-safe form of an axis value; a hash suffix keeps distinct names distinct."""
    s = re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._") or "x"
    if s != name:
        s += "-" + hashlib.sha1(name.encode()).hexdigest()[:6]
    return s


def read_rgb(path: Path) -> np.ndarray:
    from PIL import Image

    try:
        with Image.open(path) as im:
            return np.asarray(im.convert("RGB"))
    except (OSError, ValueError) as exc:
        raise ReportError(f"{path}: unreadable image: {exc}") from None


def read_mask(path: Path) -> np.ndarray:
    """A mask PNG as bool [H, W] (> 128 of 255)."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            return np.asarray(im.convert("L")) > THRESHOLD_U8
    except (OSError, ValueError) as exc:
        raise ReportError(f"{path}: unreadable mask: {exc}") from None


def fit_mask(mask: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A bool mask at ``shape`` by the protocols' own resize (cobgs.evaluate.protocols)."""
    from cobgs.evaluate.protocols import resize_nearest as protocol_resize

    if mask.shape == tuple(shape):
        return mask
    return protocol_resize(mask.astype(np.uint8) * 255, int(shape[0]), int(shape[1])) > THRESHOLD_U8


def resize_rgb(img: np.ndarray, shape: tuple[int, int], nearest: bool = False) -> np.ndarray:
    from PIL import Image

    if img.shape[:2] == tuple(shape):
        return img
    res = Image.NEAREST if nearest else (Image.BILINEAR if shape[1] > img.shape[1] else Image.BOX)
    return np.asarray(Image.fromarray(img).resize((shape[1], shape[0]), resample=res))


def write_png(path: Path, img: np.ndarray) -> None:
    """PNG, or JPEG when ``path`` ends in .jpg."""
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    if img.dtype == np.bool_:
        img = img.astype(np.uint8) * 255
    im = Image.fromarray(np.ascontiguousarray(img))
    if path.suffix == ".jpg":
        im.save(path, quality=JPEG_QUALITY)
    else:
        im.save(path, optimize=False, compress_level=6)


def display_shape(shape: tuple[int, int]) -> tuple[int, int]:
    h, w = shape[:2]
    if w <= MAX_WIDTH_PX:
        return h, w
    return max(1, round(h * MAX_WIDTH_PX / w)), MAX_WIDTH_PX


def paint(image: np.ndarray, tp: np.ndarray, fp: np.ndarray, fn: np.ndarray) -> np.ndarray:
    """The image dimmed outside the object, FP and FN painted in two colours.

    Args:
        image: [H, W, 3] uint8.
        tp, fp, fn: [H, W] bool (FP and FN win over TP where a shrunk map has both).
    """
    f = image.astype(np.float32)
    grey = f.mean(axis=2, keepdims=True)
    out = 0.45 * (0.5 * f + 0.5 * grey)  # context only: dim, half desaturated
    out[tp] = f[tp]
    for m, rgb in ((fp, FP_RGB), (fn, FN_RGB)):
        out[m] = 0.15 * f[m] + 0.85 * np.asarray(rgb, np.float32)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def overlay(image: np.ndarray, gt: np.ndarray, pred: np.ndarray) -> np.ndarray:
    """:func:`paint` of a prediction against its GT (all [H, W], the GT's size)."""
    return paint(image, gt & pred, pred & ~gt, gt & ~pred)


def shrink_any(mask: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Downscale a bool mask so that a pixel is set when *any* pixel it covers is: a
    one-pixel error on a 4000-pixel-wide GT stays visible in a 480-pixel picture."""
    from PIL import Image

    if mask.shape == tuple(shape):
        return mask
    im = Image.fromarray(mask.astype(np.uint8) * 255).resize((shape[1], shape[0]), resample=Image.BOX)
    return np.asarray(im) > 0


def _edges(m: np.ndarray) -> np.ndarray:
    """Pixels on either side of the mask's outline (4-neighbours that differ)."""
    e = np.zeros_like(m)
    dy, dx = m[1:, :] != m[:-1, :], m[:, 1:] != m[:, :-1]
    e[1:, :] |= dy
    e[:-1, :] |= dy
    e[:, 1:] |= dx
    e[:, :-1] |= dx
    return e


def crop_window(gt: np.ndarray, errors: list[np.ndarray]) -> tuple[int, int, int]:
    """(top, left, size) of the square window shared by every method's crop.

    The window is centred on an error pixel (an outline pixel when no method errs) whose
    neighbourhood holds the most error pixels, summed over methods (or the most outline);
    among equals, the one nearest their centre of mass. Centring on the outline itself
    keeps both sides of it in view.
    """
    h, w = gt.shape
    size = int(min(max(16, min(h, w) // 3), min(h, w), 400))
    score = np.zeros((h, w), np.float64)
    for e in errors:
        score += e
    if not score.any():
        score = _edges(gt).astype(np.float64)
    if not score.any():
        return (h - size) // 2, (w - size) // 2, size
    r = size // 2
    padded = np.pad(score, ((r, size - r), (r, size - r)))
    ii = np.pad(padded.cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    # sums[y, x] = score summed over the window centred (as nearly as an even size allows) on (y, x)
    sums = (ii[size:size + h, size:size + w] - ii[:h, size:size + w] - ii[size:size + h, :w] + ii[:h, :w])
    sums = np.where(score > 0, sums, -1.0)  # centred on an error / outline pixel itself
    ys, xs = np.nonzero(sums >= sums.max() - 1e-9)
    total = score.sum()
    cy = float(np.arange(h) @ score.sum(1)) / total
    cx = float(np.arange(w) @ score.sum(0)) / total
    k = int(np.argmin((ys - cy) ** 2 + (xs - cx) ** 2))
    top = int(np.clip(ys[k] - r, 0, h - size))
    left = int(np.clip(xs[k] - r, 0, w - size))
    return top, left, size


def draw_box(img: np.ndarray, top: int, left: int, size: int, width: int) -> np.ndarray:
    out = img.copy()
    b, r = top + size - 1, left + size - 1
    c = np.asarray(CROP_RGB, np.uint8)
    out[top:top + width, left:r + 1] = c
    out[max(top, b - width + 1):b + 1, left:r + 1] = c
    out[top:b + 1, left:left + width] = c
    out[top:b + 1, max(left, r - width + 1):r + 1] = c
    return out


def crop_display(img: np.ndarray, top: int, left: int, size: int) -> np.ndarray:
    """The crop, scaled to :data:`CROP_DISPLAY_PX` (nearest when enlarging: pixels stay
    visible, which is the point of a boundary crop)."""
    c = img[top:top + size, left:left + size]
    n = CROP_DISPLAY_PX
    return resize_rgb(c, (n, n), nearest=size < n)


@dataclass
class MethodPictures:
    method: str
    label: str
    files: dict = field(default_factory=dict)  # kind -> relative URL
    iou: Optional[float] = None
    biou: Optional[float] = None
    fp_px: Optional[int] = None
    fn_px: Optional[int] = None
    note: str = ""


@dataclass
class PictureSet:
    scene: str
    object: str
    view: str
    files: dict = field(default_factory=dict)  # "image", "gt" -> relative URL
    methods: list[MethodPictures] = field(default_factory=list)
    crop: Optional[tuple[int, int, int]] = None  # in GT pixels
    gt_size: Optional[tuple[int, int]] = None
    notes: list[str] = field(default_factory=list)
    id: str = ""

    def compare_data(self) -> dict:
        """What the page's comparison slider switches between: {method: {kind: URL}}."""
        return {"methods": {m.method: dict(m.files) for m in self.methods if m.files}}

    @property
    def kinds(self) -> list[str]:
        """The per-method picture kinds present for at least one method, in display order."""
        have = {k for m in self.methods for k in m.files}
        return [k for k in KINDS if k in have]


KINDS = ("pred", "overlay", "crop", "object", "removed", "turn_object", "turn_removed")
KIND_LABELS = {"pred": "predicted mask", "overlay": "errors (FP / FN)", "crop": "boundary crop",
               "object": "object alone", "removed": "object removed", "turn_object": "object alone, turning",
               "turn_removed": "object removed, turning"}


def compose(ps: PictureSet, image: Optional[np.ndarray], gt: Optional[np.ndarray],
            preds: dict, renders: dict, out_dir: Path, url_base: str) -> None:
    """Write the pictures of one (scene, object, view) under ``out_dir`` and record their
    URLs (``url_base`` + file) in ``ps``.

    Args:
        image: [H, W, 3] uint8 held-out image, or None.
        gt: [H', W'] bool GT mask at the protocol's size, or None.
        preds: method -> [h, w] bool predicted mask (any size).
        renders: method -> {"object": array, "removed": array} uint8 RGB renders.
    """
    def put(rel: str, img: np.ndarray) -> str:
        write_png(out_dir / rel, img)
        return f"{url_base}/{rel}"

    ref_shape = gt.shape if gt is not None else (image.shape[:2] if image is not None else None)
    if image is not None:
        ps.files["image"] = put("image.jpg", resize_rgb(image, display_shape(image.shape)))
    if gt is not None:
        ps.gt_size = gt.shape
        ps.files["gt"] = put("gt.png", fit_mask(gt, display_shape(gt.shape)))
    back = None
    if gt is not None:
        back = resize_rgb(image, gt.shape) if image is not None else np.full(gt.shape + (3,), 128, np.uint8)
    fitted = {m: fit_mask(p, gt.shape) for m, p in preds.items()} if gt is not None else {}
    if gt is not None and fitted:
        ps.crop = crop_window(gt, [(p ^ gt) for p in fitted.values()])
    if gt is not None:
        dshape = display_shape(gt.shape)
        back_d = resize_rgb(back, dshape)
        scale = dshape[1] / gt.shape[1]
    for mp in ps.methods:
        d = slug(mp.method)
        if mp.method in preds:
            p = preds[mp.method]
            shape = ref_shape or p.shape
            mp.files["pred"] = put(f"{d}/pred.png", fit_mask(fit_mask(p, shape), display_shape(shape)))
        if mp.method in fitted:
            p = fitted[mp.method]
            tp, fp, fn = gt & p, p & ~gt, gt & ~p
            mp.fp_px, mp.fn_px = int(np.count_nonzero(fp)), int(np.count_nonzero(fn))
            top, left, size = ps.crop
            win = (slice(top, top + size), slice(left, left + size))
            mp.files["crop"] = put(f"{d}/crop.png", crop_display(paint(back[win], tp[win], fp[win], fn[win]),
                                                                 0, 0, size))
            # The page-size overlay is painted at page size from error maps shrunk with
            # "any", so that thin boundary errors do not average away.
            disp = paint(back_d, fit_mask(tp, dshape), shrink_any(fp, dshape), shrink_any(fn, dshape))
            disp = draw_box(disp, round(top * scale), round(left * scale), max(2, round(size * scale)),
                            max(1, round(disp.shape[1] / 240)))
            mp.files["overlay"] = put(f"{d}/overlay.png", disp)
        for kind in ("object", "removed"):
            r = renders.get(mp.method, {}).get(kind)
            if r is not None:
                mp.files[kind] = put(f"{d}/{kind}.jpg", resize_rgb(r, display_shape(r.shape)))
