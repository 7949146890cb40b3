"""Memory-bank bookkeeping: which frames and pointers reach memory attention, per step."""

from __future__ import annotations

import numpy as np
import pytest

from cobgs.masks.encoder_cache import EncoderCache
from cobgs.masks.manifest import Sam2Config, load_manifest
from cobgs.masks.memory_bank import FrameMemory, MemoryBank
from cobgs.masks.postprocess import sine_pe_1d
from cobgs.masks.sam2_models import Sam2Models
from cobgs.masks.session import SessionOptions
from cobgs.masks.video import VideoPredictor

from . import scenes


def _fm(v: float) -> FrameMemory:
    return FrameMemory(np.full((4096, 64), v, np.float32), np.full(256, v, np.float32), 1.0,
                       np.zeros((256, 256), np.float32))


def _bank(num_frames=40, **cfg) -> MemoryBank:
    rng = np.random.default_rng(0)
    proj = (rng.standard_normal((64, 256)).astype(np.float32), np.zeros(64, np.float32))
    b = MemoryBank(Sam2Config(**cfg), num_frames,
                   rng.standard_normal((7, 64)).astype(np.float32), proj)
    b.maskmem_pos = np.zeros((4096, 64), np.float32)
    return b


def test_forward_window_slots_and_pointers():
    b = _bank()
    b.add_conditioning(10, _fm(10))
    for t in range(11, 30):
        b.add_tracked(t, _fm(t))
    rec = b.select(30, reverse=False)
    # conditioning frame at slot 0, then frames 24..29 at slots 1..6 (oldest first)
    assert rec.memory == [(10, 0), (24, 1), (25, 2), (26, 3), (27, 4), (28, 5), (29, 6)]
    # pointers: the conditioning frame (distance 20), then the 15 previous frames
    assert rec.pointers[0] == (10, 20)
    assert rec.pointers[1:] == [(30 - d, d) for d in range(1, 16)]
    mem = b.build(rec)
    assert mem.memory.shape == (7 * 4096, 1, 64) and mem.ptr_tokens.shape == (16 * 4, 1, 64)
    # memory blocks are fed in the selection order; each pointer is 4 consecutive tokens
    assert mem.memory[0, 0, 0] == 10 and mem.memory[4096 * 6, 0, 0] == 29
    assert np.all(mem.ptr_tokens[4:8, 0] == 29)


def test_backward_window_is_mirrored():
    b = _bank()
    b.add_conditioning(30, _fm(30))
    for t in range(29, 20, -1):
        b.add_tracked(t, _fm(t))
    rec = b.select(20, reverse=True)
    assert rec.memory == [(30, 0), (26, 1), (25, 2), (24, 3), (23, 4), (22, 5), (21, 6)]
    # signed distance is (frame - t) * -1 when tracking backwards
    assert rec.pointers[0] == (30, 10)
    assert rec.pointers[1:] == [(20 + d, d) for d in range(1, 10)]


def test_missing_frames_skipped_and_future_conditioning_pointer_excluded():
    b = _bank()
    b.add_conditioning(5, _fm(5))
    b.add_conditioning(12, _fm(12))  # a stage-2 style prompt ahead of the current frame
    for t in (6, 7, 9):
        b.add_tracked(t, _fm(t))
    rec = b.select(10, reverse=False)
    assert rec.memory == [(5, 0), (12, 0), (6, 3), (7, 4), (9, 6)]
    assert [t for t, _ in rec.pointers] == [5, 9, 7, 6]  # 12 is in the future: no pointer


def test_pointer_window_bounded_by_sequence_and_max_ptrs():
    b = _bank(num_frames=5)
    b.add_conditioning(0, _fm(0))
    for t in range(1, 4):
        b.add_tracked(t, _fm(t))
    rec = b.select(4, reverse=False)
    # min(num_frames, 16) - 1 = 4 previous frames may be pointers; only 3 are tracked
    assert rec.pointers == [(0, 4), (3, 1), (2, 2), (1, 3)]


def test_sam21_pointer_positions_are_projected_sine():
    b = _bank(num_frames=40)
    dist = np.array([20, 1, 2], np.float32)
    w, bias = b.tpos_proj
    want = sine_pe_1d(dist / 15.0, 256) @ w.T + bias
    np.testing.assert_allclose(b.pointer_positions(dist), want, rtol=1e-6)
    # the sine encoding itself: first half sin, second half cos, dim_t = 10000^(2*(k//2)/128)
    k = np.arange(128)
    ref = np.concatenate([np.sin(3.0 / 10000 ** (2 * (k // 2) / 128)),
                          np.cos(3.0 / 10000 ** (2 * (k // 2) / 128))])
    np.testing.assert_allclose(sine_pe_1d(np.array([3.0]), 256)[0], ref, rtol=1e-5, atol=1e-6)


def test_sam20_pointer_positions_are_zero():
    b = _bank(add_tpos_enc_to_obj_ptrs=False, proj_tpos_enc_in_obj_ptrs=False)
    assert not b.pointer_positions(np.array([1, 5], np.float32)).any()


def test_temporal_encoding_index_per_slot():
    b = _bank()
    b.maskmem_pos = np.ones((4096, 64), np.float32)
    b.add_conditioning(0, _fm(0))
    b.add_tracked(1, _fm(1))
    mem = b.build(b.select(2, reverse=False))
    # slot 0 uses maskmem_tpos_enc[6]; the previous frame (slot 6) uses index 0
    np.testing.assert_allclose(mem.memory_pos[0, 0], 1 + b.maskmem_tpos_enc[6])
    np.testing.assert_allclose(mem.memory_pos[4096, 0], 1 + b.maskmem_tpos_enc[0])


# -------------------------------------------------------------------------------------
# Through the graphs: what actually reaches memory attention (input shapes traced)
# -------------------------------------------------------------------------------------
@pytest.mark.parametrize("models", ["models_dir", "models_v20"])
def test_instrumented_propagation_forward_and_backward(request, tmp_path, models):
    root = request.getfixturevalue(models)
    seq = [scenes.Frame("red", x=10 + i) for i in range(12)]
    paths, _ = scenes.write_sequence(tmp_path / "seq", seq)
    sam = Sam2Models(load_manifest(root).sam2, SessionOptions(trace_shapes=True))
    cache = EncoderCache(sam, paths)
    pred = VideoPredictor(sam, cache)
    pred.add_prompt(4, 1, box=(14, 16, 26, 28))
    fwd = [f for f, _ in pred.propagate(4, 11)]
    bwd = [f for f, _ in pred.propagate(4, 0, reverse=True)]
    assert fwd == list(range(4, 12)) and bwd == [4, 3, 2, 1, 0]
    steps = pred.banks[1].steps
    assert [s.frame for s in steps] == [5, 6, 7, 8, 9, 10, 11, 3, 2, 1, 0]
    # forward step onto frame 8: cond 4 + frames 5, 6, 7 at slots 4, 5, 6
    s8 = steps[3]
    assert s8.memory == [(4, 0), (5, 4), (6, 5), (7, 6)]
    assert s8.pointers == [(4, 4), (7, 1), (6, 2), (5, 3)]
    # backward step onto frame 1: the window mirrors to frames 7..2 (slot 1 = frame 7);
    # the forward pass's outputs 5..7 are still in the bank, as upstream, and 4 is cond
    s1 = steps[9]
    assert s1.reverse
    assert s1.memory == [(4, 0), (7, 1), (6, 2), (5, 3), (3, 5), (2, 6)]
    assert s1.pointers == [(4, 3), (2, 1), (3, 2)] + [(t, t - 1) for t in range(5, 12)]
    # the graph saw exactly those token counts, one call per tracked frame
    att = sam.sessions["memory_attention"].stats
    assert att.calls == len(steps)
    for s, shapes in zip(steps, att.shapes):
        assert shapes["memory"] == (4096 * len(s.memory), 1, 64)
        assert shapes["obj_ptr_tokens"] == (4 * len(s.pointers), 1, 64)
    # graphs: decoder and memory encoder once per frame (prompt frame included)
    calls = sam.call_counts()
    assert calls["mask_decoder"] == calls["memory_encoder"] == 12
    assert calls["image_encoder"] == 12 and cache.max_encodes_per_frame() == 1
    # the backward pass starts at the prompt frame, whose stored output is reused:
    # no frame is encoded or even looked up twice
    assert sorted(cache.encodes) == list(range(12)) and cache.hits == 0
