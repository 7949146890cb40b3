"""Per-frame cache of image-encoder outputs, so the encoder runs at most once per frame.

About 20 MB a frame (1024-input SAM2): the most recent frames stay in memory up to a byte
budget; older ones are spilled to ``.npy`` files in a private temporary folder and read
back memory-mapped, so long sequences neither re-encode nor exhaust RAM.
"""

from __future__ import annotations

import os
import tempfile
from collections import Counter, OrderedDict
from pathlib import Path
from typing import Dict, Optional, Sequence, Tuple, Union

import numpy as np

from cobgs.masks.images import load_rgb, to_model_input
from cobgs.masks.sam2_models import EncodedFrame, Sam2Models

_FIELDS = ("feats", "pos", "hr0", "hr1")


class EncoderCache:
    """Encodes frames on first use and serves every later request from the cache.

    Args:
        models: the SAM2 sessions.
        frames: image paths, or RGB uint8 [H, W, 3] arrays, in sequence order.
        max_bytes_in_memory: budget for in-memory entries before spilling to disk.
    """

    def __init__(
        self,
        models: Sam2Models,
        frames: Sequence[Union[str, os.PathLike, np.ndarray]],
        max_bytes_in_memory: int = 2 << 30,
    ):
        self.models = models
        self.frames = list(frames)
        self.max_bytes = int(max_bytes_in_memory)
        self._ram: "OrderedDict[int, EncodedFrame]" = OrderedDict()
        self._ram_bytes = 0
        self._disk: Dict[int, Path] = {}
        self._tmp: Optional[tempfile.TemporaryDirectory] = None
        self._sizes: Dict[int, Tuple[int, int]] = {}
        self.encodes: Counter = Counter()  # frame -> encoder runs
        self.hits = 0

    def __len__(self) -> int:
        return len(self.frames)

    def rgb(self, idx: int) -> np.ndarray:
        src = self.frames[idx]
        return src if isinstance(src, np.ndarray) else load_rgb(src)

    def size_hw(self, idx: int) -> Tuple[int, int]:
        """(height, width) of frame ``idx`` at its own (training) resolution."""
        if idx not in self._sizes:
            src = self.frames[idx]
            if isinstance(src, np.ndarray):
                self._sizes[idx] = src.shape[:2]
            else:
                from cobgs.masks.images import image_size

                self._sizes[idx] = image_size(src)
        return self._sizes[idx]

    def get(self, idx: int) -> EncodedFrame:
        if idx in self._ram:
            self.hits += 1
            self._ram.move_to_end(idx)
            return self._ram[idx]
        if idx in self._disk:
            self.hits += 1
            d = self._disk[idx]
            return EncodedFrame(*(np.load(d / f"{k}.npy", mmap_mode="r") for k in _FIELDS))
        rgb = self.rgb(idx)
        self._sizes[idx] = rgb.shape[:2]
        enc = self.models.encode(to_model_input(rgb, self.models.preprocess))
        self.encodes[idx] += 1
        self._ram[idx] = enc
        self._ram_bytes += enc.nbytes
        self._spill()
        return enc

    def _spill(self) -> None:
        while self._ram_bytes > self.max_bytes and len(self._ram) > 1:
            idx, enc = self._ram.popitem(last=False)
            self._ram_bytes -= enc.nbytes
            if self._tmp is None:
                self._tmp = tempfile.TemporaryDirectory(prefix="cobgs-enc-")
            d = Path(self._tmp.name) / str(idx)
            d.mkdir()
            for k in _FIELDS:
                np.save(d / f"{k}.npy", getattr(enc, k))
            self._disk[idx] = d

    def close(self) -> None:
        self._ram.clear()
        self._disk.clear()
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None

    def max_encodes_per_frame(self) -> int:
        return max(self.encodes.values(), default=0)
