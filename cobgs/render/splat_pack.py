"""A compact, quantised form of Gaussians for the report's WebGL viewer (SH degree 0).

Planar arrays, little-endian, 21 bytes per Gaussian:

=========  ==========  =======================================================================
field      type        meaning
=========  ==========  =======================================================================
position   uint16 x 3  linear in the box [lo, hi] of every Gaussian's mean (per axis)
log scale  uint16 x 3  linear in [ls_lo, ls_hi], the range of the log standard deviations
rotation   int8 x 4    the unit (w, x, y, z) quaternion x 127, sign chosen so that w >= 0
colour     uint8 x 3   degree-0 colour max(0.5 + C0·sh0, 0), linear in [0, rgb_hi]
opacity    uint8       sigmoid(opacity logit) x 255
label      uint8       0 = scene, 1 = the segmented object (any small integer)
=========  ==========  =======================================================================

The header (a JSON-able dict) holds the count and the ranges. :func:`unpack` is the exact
inverse the viewer computes in JavaScript (``reports/static/viewer.js``), so a test can
render the decoded Gaussians with :func:`cobgs.render.rasterize.rasterize` and compare with the
browser's picture; :func:`quantisation_error` says what the packing alone costs.

When a model is larger than a byte budget, :func:`keep_order` ranks the Gaussians by
opacity x projected area (the product of the two largest standard deviations): the ones a
viewer misses least come first.
"""

from __future__ import annotations

import math
from typing import Optional

import numpy as np

from cobgs.errors import InputError

BYTES_PER_GAUSSIAN = 6 + 6 + 4 + 3 + 1 + 1
FIELDS = (("position", np.uint16, 3), ("log_scale", np.uint16, 3), ("rotation", np.int8, 4),
          ("rgb", np.uint8, 3), ("opacity", np.uint8, 1), ("label", np.uint8, 1))
C0 = 0.28209479177387814


def _arrays(model) -> dict:
    d = model.data
    return {
        "means": d["means"].detach().double().cpu().numpy(),
        "log_scales": d["log_scales"].detach().double().cpu().numpy(),
        "quats": d["quats"].detach().double().cpu().numpy(),
        "opacity": 1.0 / (1.0 + np.exp(-d["opacity_logits"].detach().double().cpu().numpy())),
        "rgb": np.maximum(d["sh0"].detach().double().cpu().numpy()[:, 0, :] * C0 + 0.5, 0.0),
    }


def keep_order(model) -> np.ndarray:
    """Indices of the Gaussians, most visible first: opacity x the product of the two
    largest standard deviations (a Gaussian's screen area up to the view), ties by index."""
    d = model.data
    s = np.sort(d["log_scales"].detach().double().cpu().numpy(), axis=1)
    opacity = 1.0 / (1.0 + np.exp(-d["opacity_logits"].detach().double().cpu().numpy()))
    score = np.log(np.clip(opacity, 1e-12, None)) + s[:, 1] + s[:, 2]
    score = np.nan_to_num(score, nan=-np.inf)
    return np.lexsort((np.arange(len(score)), -score))


def _unit(lo: float, hi: float) -> float:
    return (hi - lo) if hi > lo else 1.0


def pack(model, labels: Optional[np.ndarray] = None, keep: Optional[np.ndarray] = None) -> tuple[dict, bytes]:
    """(header, payload) of ``model`` (its ``keep`` indices, default all).

    Args:
        model: :class:`cobgs.gaussians.model.GaussianModel` (higher SH bands are dropped).
        labels: [N] small non-negative integers (default zeros).
        keep: indices to pack, in the order to store them.
    """
    a = _arrays(model)
    n_all = len(a["means"])
    lab = np.zeros(n_all, np.int64) if labels is None else np.asarray(labels).astype(np.int64)
    if lab.shape != (n_all,) or (n_all and (lab.min() < 0 or lab.max() > 255)):
        raise InputError(f"labels must be [{n_all}] integers in 0..255, got shape {lab.shape}")
    idx = np.arange(n_all) if keep is None else np.asarray(keep, np.int64)
    means, ls, q = a["means"][idx], a["log_scales"][idx], a["quats"][idx]
    op, rgb, lab = a["opacity"][idx], a["rgb"][idx], lab[idx]
    finite = np.isfinite(means).all(1) & np.isfinite(ls).all(1) & np.isfinite(q).all(1) & np.isfinite(op) \
        & np.isfinite(rgb).all(1)
    if not finite.all():
        raise InputError(f"{int((~finite).sum())} Gaussian(s) with a non-finite parameter: nothing to pack")
    n = len(idx)
    lo = means.min(0) if n else np.zeros(3)
    hi = means.max(0) if n else np.zeros(3)
    ls_lo = float(ls.min()) if n else 0.0
    ls_hi = float(ls.max()) if n else 0.0
    rgb_hi = max(1.0, float(rgb.max()) if n else 1.0)
    pos_q = np.rint((means - lo) / np.where(hi > lo, hi - lo, 1.0) * 65535).clip(0, 65535).astype("<u2")
    ls_q = np.rint((ls - ls_lo) / _unit(ls_lo, ls_hi) * 65535).clip(0, 65535).astype("<u2")
    qn = q / np.clip(np.linalg.norm(q, axis=1, keepdims=True), 1e-12, None)
    qn = np.where(qn[:, :1] < 0, -qn, qn)
    rot_q = np.rint(qn * 127).clip(-127, 127).astype(np.int8)
    rgb_q = np.rint(rgb / rgb_hi * 255).clip(0, 255).astype(np.uint8)
    op_q = np.rint(op * 255).clip(0, 255).astype(np.uint8)
    payload = b"".join(x.tobytes() for x in (pos_q, ls_q, rot_q, rgb_q, op_q, lab.astype(np.uint8)))
    assert len(payload) == n * BYTES_PER_GAUSSIAN
    header = {"count": n, "lo": [float(v) for v in lo], "hi": [float(v) for v in hi],
              "ls_lo": ls_lo, "ls_hi": ls_hi, "rgb_hi": rgb_hi, "bytes_per_gaussian": BYTES_PER_GAUSSIAN}
    return header, payload


def unpack(header: dict, payload: bytes) -> dict:
    """The decoded arrays (float32, as the viewer holds them): means [N, 3], log_scales
    [N, 3], quats [N, 4] (unit), rgb [N, 3], opacity [N], labels [N] (uint8)."""
    n = int(header["count"])
    if len(payload) != n * BYTES_PER_GAUSSIAN:
        raise InputError(f"packed splats: expected {n * BYTES_PER_GAUSSIAN} bytes for {n} Gaussians, "
                         f"got {len(payload)}")
    out, at = {}, 0
    for name, dtype, k in FIELDS:
        size = n * k * np.dtype(dtype).itemsize
        out[name] = np.frombuffer(payload, np.dtype(dtype).newbyteorder("<"), count=n * k, offset=at).reshape(n, k)
        at += size
    lo, hi = np.asarray(header["lo"]), np.asarray(header["hi"])
    ls_lo, ls_hi = float(header["ls_lo"]), float(header["ls_hi"])
    q = out["rotation"].astype(np.float64) / 127.0
    q = q / np.clip(np.linalg.norm(q, axis=1, keepdims=True), 1e-12, None)
    return {
        "means": (lo + out["position"] / 65535.0 * (hi - lo)).astype(np.float32),
        "log_scales": (ls_lo + out["log_scale"] / 65535.0 * (ls_hi - ls_lo)).astype(np.float32),
        "quats": q.astype(np.float32),
        "rgb": (out["rgb"] / 255.0 * float(header["rgb_hi"])).astype(np.float32),
        "opacity": (out["opacity"][:, 0] / 255.0).astype(np.float32),
        "labels": out["label"][:, 0].copy(),
    }


def unpacked_model(header: dict, payload: bytes):
    """The decoded Gaussians as a degree-0 :class:`~cobgs.gaussians.model.GaussianModel` whose
    colour (max(0.5 + C0·sh0, 0)) is the decoded colour: what the viewer draws."""
    import torch

    from cobgs.gaussians.model import GaussianModel

    d = unpack(header, payload)
    op = np.clip(d["opacity"].astype(np.float64), 1e-7, 1 - 1e-7)
    t = lambda x: torch.from_numpy(np.ascontiguousarray(x)).float()  # noqa: E731
    n = len(d["means"])
    return GaussianModel(t(d["means"]), t(d["log_scales"]), t(d["quats"]), t(np.log(op / (1.0 - op))),
                         t((d["rgb"].astype(np.float64) - 0.5) / C0)[:, None, :], torch.zeros(n, 0, 3))


def budget_count(n: int, max_bytes: Optional[int]) -> int:
    """How many of ``n`` Gaussians fit ``max_bytes`` (all when no budget)."""
    if max_bytes is None:
        return n
    return max(0, min(n, int(math.floor(max_bytes / BYTES_PER_GAUSSIAN))))
