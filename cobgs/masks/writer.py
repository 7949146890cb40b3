"""Atomic output: 8-bit 0/255 PNG masks named by image stem, and the JSON generation log."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Union

import numpy as np

from cobgs._atomic import write_bytes_atomic
from cobgs.errors import DataError


def _atomic_bytes(path: Path, data: bytes) -> None:
    write_bytes_atomic(path, data)  # readers never see a half-written file


def write_mask_png(path: Union[str, os.PathLike], mask: np.ndarray) -> None:
    """Write a bool/0-1 mask [H, W] as a lossless single-channel PNG of 0 and 255."""
    import cv2

    m = np.asarray(mask)
    if m.ndim != 2:
        raise DataError(f"mask must be [H, W], got {list(m.shape)}", path)
    ok, buf = cv2.imencode(".png", np.where(m > 0, 255, 0).astype(np.uint8))
    if not ok:
        raise DataError("PNG encoding failed", path)
    _atomic_bytes(Path(path), buf.tobytes())


def write_json(path: Union[str, os.PathLike], data: dict) -> None:
    _atomic_bytes(Path(path), (json.dumps(data, indent=2) + "\n").encode())
