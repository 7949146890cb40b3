"""SAM2 video propagation around the four ONNX graphs (host side of the contract).

One :class:`VideoPredictor` tracks any number of objects over one frame sequence. Each
object has its own :class:`~cobgs.masks.memory_bank.MemoryBank`; the encoder cache is
shared, so a frame is encoded once however many objects, passes or stages visit it.

Prompted frames become conditioning frames: decoded on the raw features plus
``no_mem_embed`` without memory attention, their memory encoded from the binarised mask.
Tracked frames go through memory attention, a prompt-free multimask decode, object-score
gating and the memory encoder on the sigmoid of the high-resolution logits.

A prompt on a frame the object was already tracked to is, by default, a *correction*, as
in the SAM2 video predictor that Grounded-SAM-2 ships (and the COB-GS authors ran): the
frame is decoded through memory attention (the memory selected in the direction it was
last tracked) with the prompt and the frame's previous mask logits (clamped to ±32) as the
dense mask input, single-mask unless ``multimask_output_for_tracking`` allows it; it stays
an ordinary tracked frame (later frames use it as recent memory, not as a conditioning
frame), its memory is encoded from the binarised mask, and propagation keeps it instead of
tracking it again. Every other object's output on that frame is kept too, its memory
re-encoded from its binarised mask (upstream consolidates the frame across objects).
``on_tracked="condition"`` makes such a prompt a new conditioning frame instead.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Dict, Iterator, List, Optional, Sequence, Tuple

import numpy as np

from cobgs.errors import InputError, ModelError

from cobgs.masks.encoder_cache import EncoderCache
from cobgs.masks.memory_bank import FrameMemory, MemoryBank
from cobgs.masks.postprocess import (NO_OBJ_SCORE, choose_mask, fill_holes, resize_logits,
                          round_bfloat16)
from cobgs.masks.sam2_models import EncodedFrame, Sam2Models


@dataclass
class StepTiming:
    """Seconds spent in one tracking step.

    Attributes:
        graph_s: memory attention + decoder + memory encoder graphs.
        host_s: host work around those graphs (memory bank, mask choice, resizing).
        frame_s: getting the frame's features (cache hit, or load + encode on a miss).
        host_cpu_s: CPU time of the host work (this thread), which, unlike ``host_s``,
            does not grow when other processes compete for the cores.
    """

    frame: int
    graph_s: float
    host_s: float
    frame_s: float
    host_cpu_s: float = 0.0


@dataclass
class VideoPredictor:
    """Prompt frames, propagate, and read masks back at each frame's own resolution.

    Args:
        models: the SAM2 sessions and constants.
        cache: encoder outputs per frame (also knows each frame's size).
    """

    models: Sam2Models
    cache: EncoderCache
    banks: Dict[int, MemoryBank] = field(default_factory=dict)
    # image-only exports: prompted-frame logits without a memory bank
    _image_only: Dict[Tuple[int, int], np.ndarray] = field(default_factory=dict)
    timings: List[StepTiming] = field(default_factory=list)

    @property
    def num_frames(self) -> int:
        return len(self.cache)

    # ------------------------------------------------------------------ prompts
    def _bank(self, obj_id: int) -> MemoryBank:
        if obj_id not in self.banks:
            m = self.models
            self.banks[obj_id] = MemoryBank(m.config, self.num_frames, m.tpos_enc, m.tpos_proj)
        return self.banks[obj_id]

    def _check_frame(self, frame: int) -> None:
        if not 0 <= frame < self.num_frames:
            raise InputError(f"frame index must be in [0, {self.num_frames}), got {frame}")

    def _prompt_embed(self, enc: EncodedFrame) -> np.ndarray:
        if self.models.no_mem_embed is None:
            raise ModelError("SAM2 constants lack no_mem_embed",
                             self.models.manifest.constants_path)
        return enc.feats + self.models.no_mem_embed

    def add_prompt(
        self,
        frame: int,
        obj_id: int,
        points: Optional[np.ndarray] = None,
        labels: Optional[np.ndarray] = None,
        box: Optional[Sequence[float]] = None,
        on_tracked: str = "correct",
    ) -> np.ndarray:
        """Prompt ``obj_id`` on ``frame`` with points and/or a box.

        A frame the object has not been tracked to becomes a conditioning frame. On a
        frame it has been tracked to, ``on_tracked`` decides: "correct" (SAM2's video
        predictor: a correction decoded with memory and the previous mask, kept as a
        tracked frame; see the module docstring) or "condition" (a new conditioning
        frame decoded without memory: the prompt outranks the memory, and every later
        frame attends to it as to the first prompt).

        Args:
            points: float [n, 2] (x, y) in the frame's own pixels; labels: [n] 1/0.
            box: (x0, y0, x1, y1) in the frame's own pixels; it goes first, as corners
                labelled 2 and 3 (how SAM2 was trained).

        Returns:
            bool [H, W] mask of the object on that frame.
        """
        if on_tracked not in ("correct", "condition"):
            raise InputError(f"on_tracked must be 'correct' or 'condition', got {on_tracked!r}")
        self._check_frame(frame)
        cfg = self.models.config
        h, w = self.cache.size_hw(frame)
        coords: List[np.ndarray] = []
        labs: List[np.ndarray] = []
        if box is not None:
            b = np.asarray(box, np.float32).reshape(-1)
            if b.shape != (4,) or not np.all(np.isfinite(b)):
                raise InputError(f"box must be 4 finite numbers (x0, y0, x1, y1), got {box!r}")
            coords.append(b.reshape(2, 2))
            labs.append(np.array([2, 3], np.float32))
        if points is not None:
            p = np.asarray(points, np.float32).reshape(-1, 2)
            lab = np.asarray(labels if labels is not None else np.ones(len(p)), np.float32)
            if lab.shape != (p.shape[0],):
                raise InputError(f"labels must be [{p.shape[0]}], got {list(lab.shape)}")
            if not np.isin(lab, (0, 1)).all():
                raise InputError("point labels must be 1 (positive) or 0 (negative)")
            coords.append(p)
            labs.append(lab)
        if not coords or sum(len(c) for c in coords) == 0:
            raise InputError("a prompt needs a box or at least one point")
        xy = np.concatenate(coords) * np.array([cfg.image_size / w, cfg.image_size / h],
                                                np.float32)
        lab = np.concatenate(labs)
        enc = self.cache.get(frame)
        bank = self.banks.get(obj_id)
        if (on_tracked == "correct" and bank is not None and frame in bank.non_cond
                and frame not in bank.cond):
            return self._correct(frame, obj_id, enc, xy, lab, (h, w))
        multimask = cfg.multimask_output_in_sam and (
            cfg.multimask_min_pt_num <= len(lab) <= cfg.multimask_max_pt_num)
        dec = self.models.decode(self._prompt_embed(enc), enc, xy, lab)
        plane, ptr_plane = choose_mask(dec.masks, dec.ious, multimask, cfg.stability_delta,
                                       cfg.stability_thresh, cfg.use_multimask_token_for_obj_ptr)
        low = dec.masks[plane] if dec.object_score > 0 else np.full_like(dec.masks[plane],
                                                                         NO_OBJ_SCORE)
        filled = fill_holes(low, cfg.fill_hole_area)
        self._store_conditioning(frame, obj_id, enc, filled, dec.obj_ptr, ptr_plane,
                                 dec.object_score)
        return resize_logits(filled, (h, w)) > 0

    def _correct(self, frame: int, obj_id: int, enc: EncodedFrame, xy: np.ndarray, lab: np.ndarray,
                 size_hw: Tuple[int, int]) -> np.ndarray:
        """A prompt on a tracked frame, as SAM2's video predictor treats it (module docstring)."""
        cfg = self.models.config
        bank = self.banks[obj_id]
        reverse = bank.directions.get(frame, False)
        prev = np.clip(bank.non_cond[frame].low_res, -32.0, 32.0)
        rec = bank.select(frame, reverse)
        mem = bank.build(rec, use_pointers=self.models.layout.ptr_mode != "none")
        pix = self.models.attend(enc, mem)
        dec = self.models.decode(pix, enc, xy, lab, mask_input=prev)
        multimask = (cfg.multimask_output_in_sam and cfg.multimask_output_for_tracking
                     and cfg.multimask_min_pt_num <= len(lab) <= cfg.multimask_max_pt_num)
        plane, ptr_plane = choose_mask(dec.masks, dec.ious, multimask, cfg.stability_delta,
                                       cfg.stability_thresh, cfg.use_multimask_token_for_obj_ptr)
        low = dec.masks[plane] if dec.object_score > 0 else np.full_like(dec.masks[plane],
                                                                         NO_OBJ_SCORE)
        filled = fill_holes(low, cfg.fill_hole_area)
        ptr = (dec.obj_ptr[ptr_plane].copy() if dec.obj_ptr is not None
               else np.zeros(cfg.hidden_dim, np.float32))
        feats, _ = self._prompted_memory(enc, filled, dec.object_score)
        bank.add_tracked(frame, FrameMemory(feats, ptr, dec.object_score, filled))
        bank.kept.add(frame)
        for other_id, other in self.banks.items():  # the frame is consolidated across objects
            if other_id == obj_id or frame in other.cond or frame in other.kept:
                continue
            out = other.non_cond.get(frame)
            if out is None:
                continue
            out.maskmem, _ = self._prompted_memory(enc, out.low_res, out.object_score)
            other.kept.add(frame)
        return resize_logits(filled, size_hw) > 0

    def _prompted_memory(self, enc: EncodedFrame, low_res: np.ndarray,
                         score: float) -> Tuple[np.ndarray, np.ndarray]:
        """(memory features, memory positions) of a frame whose mask came from a prompt
        (binarised when the export says SAM2 binarises masks from points, as its video
        predictor does)."""
        cfg = self.models.config
        high = resize_logits(low_res, (cfg.image_size, cfg.image_size))
        if cfg.binarize_mask_from_pts:
            mask_for_mem = (high > 0).astype(np.float32) * cfg.sigmoid_scale + cfg.sigmoid_bias
        else:
            mask_for_mem = _scaled_sigmoid(high, cfg.sigmoid_scale, cfg.sigmoid_bias)
        feats, pos = self.models.encode_memory(enc, mask_for_mem, score)
        return (round_bfloat16(feats) if cfg.memory_bfloat16 else feats), pos

    def add_mask(self, frame: int, obj_id: int, mask: np.ndarray) -> np.ndarray:
        """Make ``frame`` a conditioning frame from a binary mask [H, W] (used as output).

        Needs ``mask_downsample_weight/bias`` in the constants (the export script writes
        them) to derive the object pointer as SAM2 does.
        """
        import cv2

        self._check_frame(frame)
        c = self.models.constants
        if "mask_downsample_weight" not in c:
            raise ModelError(
                "mask prompts need 'mask_downsample_weight' and 'mask_downsample_bias' in "
                "sam2_constants.npz (re-export with `cobgs export-onnx sam2`)",
                self.models.manifest.constants_path,
            )
        cfg = self.models.config
        h, w = self.cache.size_hw(frame)
        m = np.asarray(mask)
        if m.shape != (h, w):
            raise InputError(f"mask must be [{h}, {w}] (frame size), got {list(m.shape)}")
        s = cfg.image_size
        m1024 = cv2.resize(m.astype(np.float32), (s, s), interpolation=cv2.INTER_LINEAR) >= 0.5
        high = m1024.astype(np.float32) * 20.0 - 10.0  # mask logits used as the output
        low = cv2.resize(high, (s // 4, s // 4), interpolation=cv2.INTER_AREA)
        # SAM2 derives the pointer by decoding the mask through a learned 4x4 conv
        k = c["mask_downsample_weight"].reshape(4, 4)
        blocks = m1024.astype(np.float32).reshape(s // 4, 4, s // 4, 4)
        dense = np.einsum("iajb,ab->ij", blocks, k) + c["mask_downsample_bias"][0]
        enc = self.cache.get(frame)
        dec = self.models.decode(self._prompt_embed(enc), enc, np.zeros((0, 2), np.float32),
                                 np.zeros((0,), np.float32), mask_input=dense)
        _, ptr_plane = choose_mask(dec.masks, dec.ious, True, cfg.stability_delta,
                                   cfg.stability_thresh, cfg.use_multimask_token_for_obj_ptr)
        score = 10.0 if m1024.any() else -10.0
        self._store_conditioning(frame, obj_id, enc, low, dec.obj_ptr, ptr_plane, score)
        return m.astype(bool)

    def _store_conditioning(self, frame, obj_id, enc, filled, obj_ptr, ptr_plane, score):
        cfg = self.models.config
        if not self.models.has_video:
            self._image_only[(frame, obj_id)] = filled
            return
        feats, pos = self._prompted_memory(enc, filled, score)
        bank = self._bank(obj_id)
        if bank.maskmem_pos is None:
            bank.maskmem_pos = pos
        ptr = obj_ptr[ptr_plane] if obj_ptr is not None else np.zeros(cfg.hidden_dim, np.float32)
        bank.add_conditioning(frame, FrameMemory(feats, ptr.copy(), score, filled))
        bank.kept.discard(frame)

    # ------------------------------------------------------------------ tracking
    def track(self, frame: int, obj_id: int, reverse: bool) -> FrameMemory:
        """One propagation step of one object onto ``frame``."""
        self.models.require_video()
        bank = self.banks.get(obj_id)
        if bank is None or not bank.cond:
            raise InputError(f"object {obj_id} has no prompted frame; add a prompt first")
        cfg = self.models.config
        sessions = self.models.sessions
        t0 = time.perf_counter()
        enc = self.cache.get(frame)  # frame loading + encoder on a miss: timed apart
        t1, c1 = time.perf_counter(), time.thread_time()
        g1 = sum(s.stats.seconds for s in sessions.values())
        gc1 = sum(s.stats.thread_cpu_seconds for s in sessions.values())
        rec = bank.select(frame, reverse)
        mem = bank.build(rec, use_pointers=self.models.layout.ptr_mode != "none")
        pix = self.models.attend(enc, mem)
        dec = self.models.decode(pix, enc, np.zeros((0, 2), np.float32),
                                 np.zeros((0,), np.float32))
        multimask = (cfg.multimask_output_in_sam and cfg.multimask_output_for_tracking
                     and cfg.multimask_min_pt_num <= 0 <= cfg.multimask_max_pt_num)
        plane, ptr_plane = choose_mask(dec.masks, dec.ious, multimask, cfg.stability_delta,
                                       cfg.stability_thresh, cfg.use_multimask_token_for_obj_ptr)
        low = dec.masks[plane] if dec.object_score > 0 else np.full_like(dec.masks[plane],
                                                                         NO_OBJ_SCORE)
        if dec.object_score > 0:
            high = resize_logits(low, (cfg.image_size, cfg.image_size))
            mask_for_mem = _scaled_sigmoid(high, cfg.sigmoid_scale, cfg.sigmoid_bias)
        else:  # sigmoid(-1024) is exactly 0 in float32: skip the 1024x1024 work
            mask_for_mem = np.full((cfg.image_size, cfg.image_size), cfg.sigmoid_bias,
                                   np.float32)
        feats, _ = self.models.encode_memory(enc, mask_for_mem, dec.object_score)
        if cfg.memory_bfloat16:
            feats = round_bfloat16(feats)
        ptr = (dec.obj_ptr[ptr_plane].copy() if dec.obj_ptr is not None
               else np.zeros(cfg.hidden_dim, np.float32))
        out = FrameMemory(feats, ptr, dec.object_score, fill_holes(low, cfg.fill_hole_area))
        bank.add_tracked(frame, out)
        bank.directions[frame] = reverse
        graphs = sum(s.stats.seconds for s in sessions.values()) - g1
        host = time.perf_counter() - t1 - graphs
        graph_cpu = sum(s.stats.thread_cpu_seconds for s in sessions.values()) - gc1
        host_cpu = time.thread_time() - c1 - graph_cpu
        self.timings.append(StepTiming(frame, graphs, host, t1 - t0, host_cpu))
        return out

    def propagate(
        self,
        start: int,
        end: Optional[int] = None,
        reverse: bool = False,
        obj_ids: Optional[Sequence[int]] = None,
    ) -> Iterator[Tuple[int, Dict[int, np.ndarray]]]:
        """Track from ``start`` to ``end`` (inclusive) and yield ``(frame, {obj: mask})``.

        Conditioning frames and corrected frames (a prompt on a tracked frame) on the way
        yield their stored masks without running a graph. ``end`` defaults to the last
        frame (first when ``reverse``).
        """
        self.models.require_video()
        self._check_frame(start)
        end = (0 if reverse else self.num_frames - 1) if end is None else end
        self._check_frame(end)
        ids = list(self.banks) if obj_ids is None else list(obj_ids)
        order = range(start, end - 1, -1) if reverse else range(start, end + 1)
        for frame in order:
            masks = {}
            for obj in ids:
                bank = self.banks[obj]
                out = bank.cond.get(frame)
                if out is None and frame in bank.kept:
                    out = bank.non_cond[frame]
                if out is None:
                    out = self.track(frame, obj, reverse)
                bank.directions[frame] = reverse  # as upstream's frames-tracked record
                masks[obj] = self._to_frame(frame, out.low_res)
            yield frame, masks

    # ------------------------------------------------------------------ reading
    def _to_frame(self, frame: int, low_res: np.ndarray) -> np.ndarray:
        return resize_logits(low_res, self.cache.size_hw(frame)) > 0

    def mask(self, frame: int, obj_id: int) -> Optional[np.ndarray]:
        """bool [H, W] current mask of ``obj_id`` on ``frame``, or None if never reached."""
        if (frame, obj_id) in self._image_only:
            return self._to_frame(frame, self._image_only[(frame, obj_id)])
        bank = self.banks.get(obj_id)
        out = bank.output(frame) if bank is not None else None
        return None if out is None else self._to_frame(frame, out.low_res)

    def union_mask(self, frame: int) -> Optional[np.ndarray]:
        """Union over objects of their masks on ``frame`` (None if no object reached it)."""
        masks = [m for m in (self.mask(frame, o) for o in self.object_ids()) if m is not None]
        if not masks:
            return None
        return np.logical_or.reduce(masks)

    def object_ids(self) -> List[int]:
        ids = list(self.banks)
        ids += [o for (_, o) in self._image_only if o not in ids]
        return ids


def _scaled_sigmoid(x: np.ndarray, scale: float, bias: float) -> np.ndarray:
    """sigmoid(x) * scale + bias; with scale 20, bias -10 this is 10 * tanh(x / 2)."""
    if scale == 20.0 and bias == -10.0:
        out = np.multiply(x, np.float32(0.5), dtype=np.float32)
        np.tanh(out, out=out)
        out *= np.float32(10.0)
        return out
    return (scale / (1.0 + np.exp(-x)) + bias).astype(np.float32)
