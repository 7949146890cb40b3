"""The SAM2 memory bank: per-object bookkeeping keyed by frame index.

Holds, for one tracked object, the outputs of its conditioning (prompted) frames and of the
frames tracked so far, and builds the inputs of the memory-attention graph for the next
frame exactly as the released video predictor selects them:

* spatial memories: every conditioning frame at temporal slot 0, then the frames 6..1
  before the current one (after it when tracking backwards) at slots 1..6, missing ones
  skipped; position = ``maskmem_pos_enc + maskmem_tpos_enc[num_maskmem - 1 - slot]``;
* object pointers: conditioning frames not in the future, then up to
  ``min(num_frames, max_obj_ptrs) - 1`` previous frames; each 256-d pointer becomes 4
  tokens of 64; position zero (SAM2.0) or a projected sine encoding of the signed frame
  distance divided by ``min(num_frames, max_obj_ptrs) - 1`` (SAM2.1).

Every selection is recorded in :attr:`MemoryBank.steps` so tests and benchmarks can see
which frames reached memory attention.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, List, Optional, Tuple

import numpy as np

from cobgs.masks.manifest import Sam2Config
from cobgs.masks.postprocess import sine_pe_1d

HW = 4096  # 64 x 64 memory tokens per frame


@dataclass
class FrameMemory:
    """What one frame leaves in the bank.

    Attributes:
        maskmem: float32 [4096, mem_dim] memory features (tokens in row-major h, w order).
        obj_ptr: float32 [hidden_dim] object pointer.
        object_score: the decoder's object-score logit.
        low_res: float32 [256, 256] output logits (holes filled), for the frame's mask.
    """

    maskmem: np.ndarray
    obj_ptr: np.ndarray
    object_score: float
    low_res: np.ndarray


@dataclass
class StepRecord:
    """Which memories one tracking step attended to."""

    frame: int
    reverse: bool
    memory: List[Tuple[int, int]]  # (frame, temporal slot), in the order fed
    pointers: List[Tuple[int, int]]  # (frame, signed/unsigned distance), in the order fed


@dataclass
class MemoryInputs:
    """Arrays for the memory-attention graph (shapes in the contract's hw1c layout)."""

    memory: np.ndarray  # [4096*M, 1, mem_dim]
    memory_pos: np.ndarray  # [4096*M, 1, mem_dim]
    ptr_tokens: np.ndarray  # [4*P, 1, mem_dim]
    ptr_pos: np.ndarray  # [4*P, 1, mem_dim]


@dataclass
class MemoryBank:
    """Memory of one tracked object over a sequence of ``num_frames`` frames.

    Args:
        config: SAM2 constants (num_maskmem, pointer settings, mem_dim).
        num_frames: frames in the sequence (bounds the pointer window, as upstream).
        maskmem_tpos_enc: float32 [num_maskmem, mem_dim] temporal encodings.
        tpos_proj: (weight [mem_dim, hidden_dim], bias [mem_dim]) of SAM2.1's pointer
            position projection, or None (SAM2.0, or no projection).
    """

    config: Sam2Config
    num_frames: int
    maskmem_tpos_enc: np.ndarray
    tpos_proj: Optional[Tuple[np.ndarray, np.ndarray]] = None
    cond: Dict[int, FrameMemory] = field(default_factory=dict)
    non_cond: Dict[int, FrameMemory] = field(default_factory=dict)
    # direction each frame was last visited in (True = reverse): a correction selects its
    # memory in that direction, as SAM2 does
    directions: Dict[int, bool] = field(default_factory=dict)
    # tracked frames that propagation keeps instead of tracking again (corrections, and the
    # other objects' outputs on a corrected frame)
    kept: set = field(default_factory=set)
    maskmem_pos: Optional[np.ndarray] = None  # [4096, mem_dim], same for every frame
    steps: List[StepRecord] = field(default_factory=list)
    _buffers: Dict[int, np.ndarray] = field(default_factory=dict, repr=False)
    _pos_cache: Dict[Tuple[int, ...], np.ndarray] = field(default_factory=dict, repr=False)

    # ------------------------------------------------------------------ storing
    def add_conditioning(self, frame: int, out: FrameMemory) -> None:
        """A prompted frame; it replaces any tracked output of the same frame."""
        self.cond[frame] = out
        self.non_cond.pop(frame, None)

    def add_tracked(self, frame: int, out: FrameMemory) -> None:
        self.non_cond[frame] = out

    def output(self, frame: int) -> Optional[FrameMemory]:
        """The frame's current output (a conditioning output wins)."""
        return self.cond.get(frame) or self.non_cond.get(frame)

    # ------------------------------------------------------------------ selecting
    def select(self, frame: int, reverse: bool) -> StepRecord:
        """The memories and pointers a tracking step at ``frame`` uses (and records)."""
        cfg = self.config
        memory: List[Tuple[int, int]] = [(t, 0) for t in self.cond]
        for slot in range(1, cfg.num_maskmem):
            t_rel = cfg.num_maskmem - slot  # slot 1 is the oldest, slot 6 the last frame
            prev = frame + t_rel if reverse else frame - t_rel
            if prev in self.non_cond:
                memory.append((prev, slot))
        pointers: List[Tuple[int, int]] = []
        max_ptrs = min(self.num_frames, cfg.max_obj_ptrs)
        sign = -1 if reverse else 1
        for t in self.cond:
            if cfg.only_obj_ptrs_in_the_past and (t < frame if reverse else t > frame):
                continue
            dist = (frame - t) * sign if cfg.use_signed_tpos_enc_to_obj_ptrs else abs(frame - t)
            pointers.append((t, dist))
        for t_diff in range(1, max_ptrs):
            t = frame + t_diff if reverse else frame - t_diff
            if t < 0 or t >= self.num_frames:
                break
            if t in self.non_cond:
                pointers.append((t, t_diff))
        rec = StepRecord(frame, reverse, memory, pointers)
        self.steps.append(rec)
        return rec

    def build(self, rec: StepRecord, use_pointers: bool = True) -> MemoryInputs:
        """Assemble the memory-attention inputs for a recorded selection.

        The returned ``memory`` array is a buffer reused by the next call: feed it to the
        graph before building again.
        """
        cfg = self.config
        if self.maskmem_pos is None:
            raise RuntimeError("memory bank has no memory yet (no conditioning frame encoded)")
        d = cfg.mem_dim
        m = len(rec.memory)
        # Reused buffers: a fresh multi-MB array per frame costs page faults every step.
        if m not in self._buffers:
            self._buffers[m] = np.empty((HW * m, 1, d), np.float32)
        memory = self._buffers[m]
        for i, (t, slot) in enumerate(rec.memory):
            src = self.cond[t] if slot == 0 else self.non_cond[t]
            memory[i * HW:(i + 1) * HW, 0] = src.maskmem
        # positions depend only on the slots: once the window is full they repeat
        slots = tuple(slot for _, slot in rec.memory)
        memory_pos = self._pos_cache.get(slots)
        if memory_pos is None:
            memory_pos = np.empty((HW * m, 1, d), np.float32)
            for i, slot in enumerate(slots):
                tpos = self.maskmem_tpos_enc[cfg.num_maskmem - slot - 1]
                np.add(self.maskmem_pos, tpos, out=memory_pos[i * HW:(i + 1) * HW, 0])
            if len(self._pos_cache) > 64:
                self._pos_cache.clear()
            self._pos_cache[slots] = memory_pos
        if not use_pointers or not rec.pointers:
            empty = np.zeros((0, 1, d), np.float32)
            return MemoryInputs(memory, memory_pos, empty, empty.copy())
        ptrs = np.stack([self.output(t).obj_ptr for t, _ in rec.pointers])  # [P, C]
        split = ptrs.shape[1] // d  # a 256-d pointer becomes 4 tokens of 64
        tokens = ptrs.reshape(-1, split, d).reshape(-1, 1, d)
        pos = self.pointer_positions(np.array([p for _, p in rec.pointers], np.float32))
        pos = np.repeat(pos, split, axis=0)[:, None, :]
        return MemoryInputs(memory, memory_pos, np.ascontiguousarray(tokens), pos)

    def pointer_positions(self, dist: np.ndarray) -> np.ndarray:
        """float32 [P] frame distances -> [P, mem_dim] pointer positions."""
        cfg = self.config
        if not cfg.add_tpos_enc_to_obj_ptrs:
            return np.zeros((dist.shape[0], cfg.mem_dim), np.float32)
        t_diff_max = max(min(self.num_frames, cfg.max_obj_ptrs) - 1, 1)
        if cfg.proj_tpos_enc_in_obj_ptrs:
            if self.tpos_proj is None:
                raise RuntimeError("SAM2.1 pointer encoding needs obj_ptr_tpos_proj constants")
            enc = sine_pe_1d(dist / np.float32(t_diff_max), cfg.hidden_dim)
            w, b = self.tpos_proj
            return (enc @ w.T + b).astype(np.float32)
        return sine_pe_1d(dist / np.float32(t_diff_max), cfg.mem_dim)
