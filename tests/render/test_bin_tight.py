"""Tight tile lists (``cobgs::bin_tiles_tight``) and the shared per-Gaussian records.

The tight lists drop the (tile, Gaussian) entries whose α >= 1/255 box misses the tile; the
blend must then produce bit-identical images, transmittance, label statistics and
gradients, because the dropped entries were never blended anywhere in their tile.
"""

from __future__ import annotations

import math

import pytest
import torch

from cobgs.render import ops
from cobgs.render import reference as ref

W, H = 70, 45


@pytest.fixture(scope="module", autouse=True)
def _loaded():
    ops.ensure_loaded()


def scene(dtype, n=400, seed=0):
    """Many overlapping Gaussians of mixed size and opacity (faint ones have boxes much
    smaller than their 3-sigma squares, opaque ones larger)."""
    g = torch.Generator().manual_seed(seed)
    rnd = lambda *s: torch.rand(*s, generator=g, dtype=dtype)  # noqa: E731
    f = 60.0
    z = 2 + 3 * rnd(n)
    means = torch.stack([(2 * rnd(n) - 1) * 0.7 * z, (2 * rnd(n) - 1) * 0.5 * z, z], -1)
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.exp(math.log(0.01) + 3.0 * rnd(n, 3))
    opacities = torch.where(rnd(n) < 0.5, 0.005 + 0.05 * rnd(n), 0.2 + 0.79 * rnd(n))
    features = rnd(n, 3)
    viewmat = torch.eye(4, dtype=dtype)
    K = torch.tensor([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]], dtype=dtype)
    m2, conics, depths, radii = ops.project(means, quats, scales, viewmat, K, W, H)
    return m2, conics, depths, radii, opacities, features


def lists(offsets, ids):
    return [ids[offsets[t]:offsets[t + 1]].tolist() for t in range(offsets.numel() - 1)]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_tight_lists_are_the_reachable_part_of_the_3sigma_lists(dtype):
    m2, conics, depths, radii, opacities, _ = scene(dtype)
    off, ids = ops.bin_tiles(m2, radii, depths, W, H)
    t_off, t_ids, prep = ops.bin_tiles_tight(m2, radii, depths, conics, opacities, W, H)
    full, tight = lists(off, ids), lists(t_off, t_ids)
    assert t_ids.numel() < 0.8 * ids.numel()  # the scene has plenty to drop
    tiles_x = (W + 15) // 16
    ys, xs = torch.meshgrid(torch.arange(H, dtype=dtype) + 0.5, torch.arange(W, dtype=dtype) + 0.5,
                            indexing="ij")
    for t, (a, b) in enumerate(zip(full, tight)):
        kept = set(b)
        assert [i for i in a if i in kept] == b  # a subsequence, same order
        assert kept <= set(a)
        x0, y0 = (t % tiles_x) * 16, (t // tiles_x) * 16
        px, py = xs[y0:y0 + 16, x0:x0 + 16], ys[y0:y0 + 16, x0:x0 + 16]
        for i in set(a) - kept:  # dropped: no pixel of the tile can reach 1/255
            ca, cb, cc = conics[i].tolist()
            dx, dy = px - m2[i, 0], py - m2[i, 1]
            power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
            alpha = torch.clamp(opacities[i] * torch.exp(power), max=0.99)
            assert float(alpha.max()) < 1.0 / 255.0, (t, i)
    assert prep.dtype == torch.uint8 and prep.shape[0] == m2.shape[0]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_blend_on_tight_lists_is_bit_identical(dtype):
    m2, conics, depths, radii, opacities, features = scene(dtype)
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=dtype)
    labels = torch.randint(-1, 3, (H, W), generator=torch.Generator().manual_seed(1), dtype=torch.int32)
    off, ids = ops.bin_tiles(m2, radii, depths, W, H)
    t_off, t_ids, prep = ops.bin_tiles_tight(m2, radii, depths, conics, opacities, W, H)
    a = ops.blend(m2, conics, opacities, features, bg, off, ids, W, H, labels, 3)
    for p in (None, prep):
        b = ops.blend(m2, conics, opacities, features, bg, t_off, t_ids, W, H, labels, 3, prep=p)
        for k in (0, 1, 3, 4):  # image, transmittance, label counts, label weights
            assert torch.equal(a[k], b[k]), k
    # Backward: the same gradients, with and without the shared records.
    g = torch.Generator().manual_seed(2)
    v_img = torch.randn(H, W, 3, generator=g, dtype=dtype)
    v_tr = torch.randn(H, W, generator=g, dtype=dtype)
    ga = torch.ops.cobgs.blend_bwd(m2, conics, opacities, features, bg, off, ids, a[1], a[2], v_img, v_tr)
    b = ops.blend(m2, conics, opacities, features, bg, t_off, t_ids, W, H, prep=prep)
    for p in (None, prep):
        gb = torch.ops.cobgs.blend_bwd(m2, conics, opacities, features, bg, t_off, t_ids, b[1], b[2],
                                       v_img, v_tr, p)
        for x, y in zip(ga, gb):
            assert torch.equal(x, y)


def test_rasterize_native_matches_reference_through_the_tight_path():
    m2, conics, depths, radii, opacities, features = scene(torch.float64, n=150, seed=3)
    bg = torch.zeros(3, dtype=torch.float64)
    off, ids, prep = ops.bin_tiles_tight(m2, radii, depths, conics, opacities, W, H)
    img, trans, *_ = ops.blend(m2, conics, opacities, features, bg, off, ids, W, H, prep=prep)
    r_off, r_ids = ref.bin_tiles_reference(m2, radii, depths, W, H)
    r_img, r_trans, *_ = ref.blend_reference(m2, conics, opacities, features, bg, r_off, r_ids, W, H)
    torch.testing.assert_close(img, r_img, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(trans, r_trans, rtol=1e-9, atol=1e-9)


def test_opcheck_bin_tiles_tight():
    m2, conics, depths, radii, opacities, _ = scene(torch.float64, n=40)
    torch.library.opcheck(torch.ops.cobgs.bin_tiles_tight.default,
                          (m2, radii, depths, conics, opacities, W, H))


def test_bad_prep_is_refused_with_a_clear_error():
    m2, conics, depths, radii, opacities, features = scene(torch.float32, n=30)
    bg = torch.zeros(3)
    off, ids, prep = ops.bin_tiles_tight(m2, radii, depths, conics, opacities, W, H)
    with pytest.raises(RuntimeError, match="prep"):
        ops.blend(m2, conics, opacities, features, bg, off, ids, W, H, prep=prep[:-1].clone())
    with pytest.raises(RuntimeError, match="prep"):
        ops.blend(m2, conics, opacities, features, bg, off, ids, W, H, prep=prep.view(torch.int8))
    # float64 inputs need float64 records (a different size)
    m2d, cod, opd = m2.double(), conics.double(), opacities.double()
    with pytest.raises(RuntimeError, match="prep"):
        ops.blend(m2d, cod, opd, features.double(), bg.double(), off, ids, W, H, prep=prep)


def test_autograd_through_blend_with_prep_matches_without():
    m2, conics, depths, radii, opacities, features = scene(torch.float64, n=60, seed=4)
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    t_off, t_ids, prep = ops.bin_tiles_tight(m2, radii, depths, conics, opacities, W, H)
    w = torch.randn(H, W, 3, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    grads = []
    for p in (None, prep):
        leaves = [t.clone().requires_grad_() for t in (m2, conics, opacities, features, bg)]
        img, trans, *_ = ops.blend(*leaves, t_off, t_ids, W, H, prep=p)
        ((img * w).sum() + trans.sum()).backward()
        grads.append([t.grad for t in leaves])
    for a, b in zip(*grads):
        assert torch.equal(a, b)
    args = (m2.clone().requires_grad_(), conics.clone().requires_grad_(),
            opacities.clone().requires_grad_(), features.clone().requires_grad_(),
            bg.clone().requires_grad_(), t_off, t_ids, W, H, None, 2, prep)
    torch.library.opcheck(torch.ops.cobgs.blend.default, args)
