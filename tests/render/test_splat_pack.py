"""The viewer's quantised Gaussians (cobgs.render.splat_pack): layout, round trip, ranking."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cobgs.render import splat_pack
from cobgs.errors import InputError
from cobgs.gaussians.model import GaussianModel


def _model(n=500, seed=0, sh_degree=1):
    g = torch.Generator().manual_seed(seed)
    k = (sh_degree + 1) ** 2 - 1
    return GaussianModel(torch.randn(n, 3, generator=g) * 2, torch.randn(n, 3, generator=g) - 3,
                         torch.randn(n, 4, generator=g), torch.randn(n, generator=g) * 2,
                         torch.randn(n, 1, 3, generator=g), torch.randn(n, k, 3, generator=g))


def test_round_trip_within_the_quantisation_steps():
    m = _model()
    labels = (np.arange(len(m)) % 3 == 0).astype(np.uint8)
    header, payload = splat_pack.pack(m, labels)
    assert len(payload) == len(m) * splat_pack.BYTES_PER_GAUSSIAN == len(m) * 21
    d = splat_pack.unpack(header, payload)
    means = m.data["means"].detach().numpy()
    step = (means.max(0) - means.min(0)) / 65535
    assert np.all(np.abs(d["means"] - means) <= step / 2 + 1e-6)
    ls = m.data["log_scales"].detach().numpy()
    assert np.abs(d["log_scales"] - ls).max() <= (ls.max() - ls.min()) / 65535 / 2 + 1e-6
    q = m.data["quats"].detach().numpy()
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    cos = np.abs((d["quats"] * q).sum(1))  # q and -q are one rotation
    assert np.degrees(2 * np.arccos(np.clip(cos, -1, 1))).max() < 2.0
    assert np.abs(d["opacity"] - torch.sigmoid(m.data["opacity_logits"]).detach().numpy()).max() <= 0.5 / 255 + 1e-6
    rgb = np.maximum(m.data["sh0"][:, 0].detach().numpy() * splat_pack.C0 + 0.5, 0)
    assert np.abs(d["rgb"] - rgb).max() <= header["rgb_hi"] / 255 / 2 + 1e-6
    assert np.array_equal(d["labels"], labels)
    # the decoded model renders the decoded colours (degree 0)
    back = splat_pack.unpacked_model(header, payload)
    assert back.sh_degree == 0
    assert torch.allclose(back.colors(torch.zeros(3)), torch.from_numpy(d["rgb"]), atol=1e-5)


def test_keep_subset_and_order():
    m = _model()
    order = splat_pack.keep_order(m)
    assert sorted(order.tolist()) == list(range(len(m)))
    s = np.sort(m.data["log_scales"].detach().numpy(), axis=1)
    score = np.log(torch.sigmoid(m.data["opacity_logits"]).detach().numpy()) + s[:, 1] + s[:, 2]
    assert np.all(np.diff(score[order]) <= 1e-9)  # most opaque x largest first
    keep = np.sort(order[:100])
    header, payload = splat_pack.pack(m, None, keep)
    d = splat_pack.unpack(header, payload)
    assert header["count"] == 100
    assert np.abs(d["means"] - m.data["means"].detach().numpy()[keep]).max() < 1e-3
    assert splat_pack.budget_count(1000, 21 * 10 + 20) == 10
    assert splat_pack.budget_count(1000, None) == 1000


def test_bad_input_is_refused():
    m = _model(n=10)
    with pytest.raises(InputError, match="labels"):
        splat_pack.pack(m, np.full(9, 1))
    with pytest.raises(InputError, match="labels"):
        splat_pack.pack(m, np.full(10, 300))
    with torch.no_grad():
        m.data["means"][3, 0] = float("nan")
    with pytest.raises(InputError, match="non-finite"):
        splat_pack.pack(m)
    header, payload = splat_pack.pack(_model(n=10))
    with pytest.raises(InputError, match="expected 210 bytes"):
        splat_pack.unpack(header, payload[:-1])


def test_empty_and_degenerate_ranges():
    m = _model(n=4)
    with torch.no_grad():
        m.data["means"][:] = 1.5  # a single point: zero range on every axis
        m.data["log_scales"][:] = -2.0
    header, payload = splat_pack.pack(m)
    d = splat_pack.unpack(header, payload)
    assert np.allclose(d["means"], 1.5) and np.allclose(d["log_scales"], -2.0)
    header, payload = splat_pack.pack(m, keep=np.array([], np.int64))
    assert header["count"] == 0 and payload == b""
