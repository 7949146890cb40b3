"""Mask-noise emulation: rates match their parameters, each error has the stated effect."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from cobgs.errors import DataError, InputError
from cobgs.data.mask_noise import (
    MaskNoiseParams,
    NoiseRecord,
    apply_mask_noise,
    mask_rng,
    noise_mask_folder,
    noise_masks,
)

OFF = dict(drop_rate=0.0, morph_rate=0.0, jitter_rate=0.0, blob_rate=0.0)


def _disc_mask(h=64, w=64, r=16.0) -> np.ndarray:
    yy, xx = np.mgrid[:h, :w]
    return ((xx + 0.5 - w / 2) ** 2 + (yy + 0.5 - h / 2) ** 2 < r * r).astype(np.uint8) * 255


def _within(count: int, n: int, p: float) -> bool:
    """count ~ Binomial(n, p) within 4.5 standard deviations (false alarm < 1e-5)."""
    sd = math.sqrt(n * p * (1 - p))
    return abs(count - n * p) <= 4.5 * sd + 1e-9


def test_rates_match_parameters():
    params = MaskNoiseParams(drop_rate=0.1, morph_rate=0.4, morph_max_px=3, dilate_fraction=0.3,
                             jitter_rate=0.25, blob_rate=0.2, blob_count_max=4, seed=7)
    n = 3000
    recs = [apply_mask_noise(np.zeros((8, 8), np.uint8), params, mask_rng(params, k))[1]
            for k in range(n)]
    dropped = sum(r.dropped for r in recs)
    assert _within(dropped, n, 0.1)
    kept = [r for r in recs if not r.dropped]
    m = len(kept)
    morphed = [r for r in kept if r.morph_px != 0]
    assert _within(len(morphed), m, 0.4)
    assert _within(sum(r.morph_px > 0 for r in morphed), len(morphed), 0.3)
    for radius in (1, 2, 3):  # radius uniform in 1..morph_max_px
        assert _within(sum(abs(r.morph_px) == radius for r in morphed), len(morphed), 1 / 3)
    assert all(1 <= abs(r.morph_px) <= 3 for r in morphed)
    assert _within(sum(r.jittered for r in kept), m, 0.25)
    blobbed = [r for r in kept if r.blobs]
    assert _within(len(blobbed), m, 0.2)
    assert {r.blobs for r in blobbed} == {1, 2, 3, 4}
    # Dropped masks carry no other error.
    assert all(r == NoiseRecord(dropped=True) for r in recs if r.dropped)


def test_zero_rates_change_nothing():
    mask = _disc_mask() > 0
    out, rec = apply_mask_noise(mask, MaskNoiseParams(**OFF), mask_rng(MaskNoiseParams(), 0))
    assert rec == NoiseRecord()
    assert out.dtype == np.uint8 and np.array_equal(out, np.where(mask, 255, 0))


@pytest.mark.parametrize("dilate", [True, False])
def test_erosion_and_dilation_move_the_boundary_by_the_radius(dilate):
    r0 = 16.0
    mask = _disc_mask(r=r0)
    for radius in (1, 2, 3):
        params = MaskNoiseParams(**{**OFF, "morph_rate": 1.0}, morph_max_px=radius,
                                 dilate_fraction=1.0 if dilate else 0.0)
        # Draw until the radius is the one under test (radius is uniform in 1..max).
        for key in range(100):
            out, rec = apply_mask_noise(mask, params, mask_rng(params, key))
            if abs(rec.morph_px) == radius:
                break
        assert rec.morph_px == (radius if dilate else -radius)
        want = math.pi * (r0 + rec.morph_px) ** 2
        # Discretised discs: area within ~one boundary-pixel ring of the ideal value.
        assert abs((out > 0).sum() - want) < 2 * math.pi * r0 * 0.6
        if dilate:
            assert np.all(out[mask > 0] > 0)
        else:
            assert np.all(mask[out > 0] > 0)


def test_jitter_stays_near_the_boundary():
    mask = _disc_mask(r=18.0)
    params = MaskNoiseParams(**{**OFF, "jitter_rate": 1.0}, jitter_amplitude_px=3.0,
                             jitter_scale_px=5.0)
    changed_any = 0
    for key in range(20):
        out, rec = apply_mask_noise(mask, params, mask_rng(params, key))
        assert rec.jittered and rec.morph_px == 0 and rec.blobs == 0
        diff = (out > 0) != (mask > 0)
        changed_any += diff.sum() > 0
        # Pixels farther than amplitude + 1 px from the boundary keep their label.
        k = np.ones((3, 3), np.uint8)
        band = cv2.dilate(mask, k, iterations=4) - cv2.erode(mask, k, iterations=4)
        assert not np.any(diff & (band == 0)), key
    assert changed_any >= 18


def test_blobs_are_small_discs_off_the_object():
    mask = _disc_mask(h=96, w=96, r=12.0)
    params = MaskNoiseParams(**{**OFF, "blob_rate": 1.0}, blob_count_max=3,
                             blob_radius_min_px=2, blob_radius_max_px=4)
    for key in range(30):
        out, rec = apply_mask_noise(mask, params, mask_rng(params, key))
        assert 1 <= rec.blobs <= 3
        assert np.all(out[mask > 0] > 0)  # the object itself is intact
        added = ((out > 0) & (mask == 0)).astype(np.uint8)
        n, _, stats, _ = cv2.connectedComponentsWithStats(added)
        assert 1 <= n - 1 <= rec.blobs  # blobs may merge with each other or the object
        assert added.sum() <= rec.blobs * math.pi * 4.5**2
        # Each blob is at most 9 px wide; merged ones at most the sum of theirs.
        assert stats[1:, cv2.CC_STAT_WIDTH].max() <= rec.blobs * (2 * 4 + 1)
        if n - 1 == rec.blobs:  # no merge: every component is one disc
            assert stats[1:, cv2.CC_STAT_WIDTH].max() <= 2 * 4 + 1


def test_dropped_masks_are_empty_and_streams_are_per_key():
    mask = _disc_mask()
    params = MaskNoiseParams(drop_rate=0.5, seed=3)
    outs, recs = noise_masks([mask] * 40, params, keys=[f"obj/{i:04d}" for i in range(40)])
    for o, r in zip(outs, recs):
        if r.dropped:
            assert not o.any()
    assert 5 < sum(r.dropped for r in recs) < 35
    # A mask's noise depends on its key only, not on the order or the company.
    rev, rev_recs = noise_masks([mask] * 40, params, keys=[f"obj/{i:04d}" for i in reversed(range(40))])
    for i in range(40):
        assert np.array_equal(outs[i], rev[39 - i]) and recs[i] == rev_recs[39 - i]
    other = noise_masks([mask] * 40, MaskNoiseParams(drop_rate=0.5, seed=4),
                        keys=[f"obj/{i:04d}" for i in range(40)])[1]
    assert other != recs


def test_folder_round_trip(tmp_path):
    src = tmp_path / "masks"
    for obj in ("ball", "box"):
        (src / obj).mkdir(parents=True)
        for i in range(6):
            cv2.imwrite(str(src / obj / f"{i:04d}.png"), _disc_mask(r=10 + i))
    params = MaskNoiseParams(drop_rate=0.3, morph_rate=0.5, jitter_rate=0.5, blob_rate=0.5, seed=1)
    log = noise_mask_folder(src, tmp_path / "noisy", params, progress=False)
    saved = json.loads((tmp_path / "noisy" / "noise.json").read_text())
    assert saved["masks"] == log and saved["params"]["seed"] == 1
    for obj in ("ball", "box"):
        for i in range(6):
            stem = f"{i:04d}"
            got = cv2.imread(str(tmp_path / "noisy" / obj / f"{stem}.png"), cv2.IMREAD_UNCHANGED)
            src_m = cv2.imread(str(src / obj / f"{stem}.png"), cv2.IMREAD_UNCHANGED)
            want, rec = apply_mask_noise(src_m, params, mask_rng(params, f"{obj}/{stem}"))
            assert np.array_equal(got, want) and log[obj][stem]["dropped"] == rec.dropped
    with pytest.raises(InputError, match="not empty"):
        noise_mask_folder(src, tmp_path / "noisy", params, progress=False)
    with pytest.raises(DataError, match="object sub-folders"):
        noise_mask_folder(tmp_path / "noisy" / "ball", tmp_path / "x", params, progress=False)


def test_bad_parameters():
    with pytest.raises(InputError, match="drop_rate"):
        MaskNoiseParams(drop_rate=1.5)
    with pytest.raises(InputError, match="blob_radius_max_px"):
        MaskNoiseParams(blob_radius_min_px=5, blob_radius_max_px=2)
    with pytest.raises(InputError, match="mask must be"):
        apply_mask_noise(np.zeros((4, 4, 3), np.uint8), MaskNoiseParams(), mask_rng(MaskNoiseParams(), 0))
