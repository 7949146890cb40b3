"""Tiny image sequences for the mask tests: a coloured square on grey, frame by frame."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Sequence, Tuple

import numpy as np

H, W = 48, 64
SIDE = 12  # the square's side, px; full area 144 px
COLOURS = {"red": (255, 0, 0), "green": (0, 255, 0)}


@dataclass(frozen=True)
class Frame:
    colour: Optional[str]  # None: object absent
    x: int = 20
    y: int = 16
    visible_rows: int = SIDE  # rows of the square left visible (occlusion from below)


def render(frame: Frame) -> Tuple[np.ndarray, np.ndarray]:
    """(RGB uint8 [H, W, 3], ground-truth bool [H, W])."""
    img = np.full((H, W, 3), 128, np.uint8)
    gt = np.zeros((H, W), bool)
    if frame.colour is not None:
        y1 = frame.y + frame.visible_rows
        img[frame.y:y1, frame.x:frame.x + SIDE] = COLOURS[frame.colour]
        gt[frame.y:y1, frame.x:frame.x + SIDE] = True
    return img, gt


def write_sequence(folder: Path, frames: Sequence[Frame]) -> Tuple[List[Path], List[np.ndarray]]:
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    paths, gts = [], []
    for i, f in enumerate(frames):
        img, gt = render(f)
        p = folder / f"{i:04d}.png"
        Image.fromarray(img).save(p)
        paths.append(p)
        gts.append(gt)
    return paths, gts


def red_gone_green(n_red=5, n_gone=5, n_green=5) -> List[Frame]:
    """Red square moving right, then absent, then back as a green square."""
    seq = [Frame("red", x=10 + 2 * i) for i in range(n_red)]
    seq += [Frame(None) for _ in range(n_gone)]
    seq += [Frame("green", x=30 - 2 * i) for i in range(n_green)]
    return seq


def iou(a: np.ndarray, b: np.ndarray) -> float:
    u = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / u) if u else 1.0
