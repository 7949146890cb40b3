"""The torch.library ops behind cobgs.rasterize (cobgs/render/ops.py): registration and per-op
gradients.

``torch.library.opcheck`` checks each op's schema (no undeclared mutation or aliasing),
its autograd registration, its fake (shape-only) kernel against the real one, and
AOT-dispatch; float64 ``gradcheck`` checks each differentiable op on its own, so a wrong
backward is pinned to its op rather than to the composed renderer.
"""

from __future__ import annotations

import pytest
import torch

from cobgs.render import ops
from cobgs.render import reference as ref

W, H = 20, 14


@pytest.fixture(scope="module", autouse=True)
def _loaded():
    ops.ensure_loaded()


def small_scene(seed=0, n=12, dtype=torch.float64):
    """A few Gaussians well inside the view (depth 2..4, σ 1..3 px, opacity 0.2..0.8)."""
    g = torch.Generator().manual_seed(seed)
    rnd = lambda *s: torch.rand(*s, generator=g, dtype=dtype)  # noqa: E731
    f = 18.0
    z = 2 + 2 * rnd(n)
    means = torch.stack([(2 * rnd(n) - 1) * 0.4 * z, (2 * rnd(n) - 1) * 0.3 * z, z], -1)
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = (1 + 2 * rnd(n, 3)) * z[:, None] / f
    opacities = 0.2 + 0.6 * rnd(n)
    features = rnd(n, 3)
    viewmat = torch.eye(4, dtype=dtype)
    K = torch.tensor([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]], dtype=dtype)
    return means, quats, scales, opacities, features, viewmat, K


def projected(dtype=torch.float64):
    means, quats, scales, opacities, features, viewmat, K = small_scene(dtype=dtype)
    m2, conics, depths, radii = ops.project(means, quats, scales, viewmat, K, W, H)
    offsets, ids = ops.bin_tiles(m2, radii, depths, W, H)
    return m2, conics, depths, radii, opacities, features, offsets, ids


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_opcheck_project(dtype):
    means, quats, scales, _, _, viewmat, K = small_scene(dtype=dtype)
    args = (means.requires_grad_(), quats.requires_grad_(), scales.requires_grad_(), viewmat,
            K, W, H, 0.01)
    torch.library.opcheck(torch.ops.cobgs.project.default, args)


def test_opcheck_project_bwd():
    means, quats, scales, _, _, viewmat, K = small_scene()
    _, _, _, radii = ops.project(means, quats, scales, viewmat, K, W, H)
    n = means.shape[0]
    args = (means, quats, scales, viewmat, K, W, H, radii, torch.randn(n, 2, dtype=torch.float64),
            torch.randn(n, 3, dtype=torch.float64), torch.randn(n, dtype=torch.float64))
    torch.library.opcheck(torch.ops.cobgs.project_bwd.default, args)


def test_opcheck_bin_tiles():
    m2, _, depths, radii, *_ = projected()
    # flat_ids has a data-dependent length (an unbacked size in the fake kernel).
    torch.library.opcheck(torch.ops.cobgs.bin_tiles.default, (m2, radii, depths, W, H))


@pytest.mark.parametrize("with_labels", [False, True])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_opcheck_blend(with_labels, dtype):
    m2, conics, _, _, opacities, features, offsets, ids = projected(dtype)
    labels = torch.randint(-1, 2, (H, W), dtype=torch.int32) if with_labels else None
    bg = torch.rand(3, dtype=dtype)
    args = (m2.requires_grad_(), conics.requires_grad_(), opacities.requires_grad_(),
            features.requires_grad_(), bg.requires_grad_(), offsets, ids, W, H, labels, 2)
    torch.library.opcheck(torch.ops.cobgs.blend.default, args)


def test_opcheck_blend_bwd():
    m2, conics, _, _, opacities, features, offsets, ids = projected()
    bg = torch.rand(3, dtype=torch.float64)
    _, trans, n_contrib, _, _ = ops.blend(m2, conics, opacities, features, bg, offsets, ids,
                                           W, H)
    args = (m2, conics, opacities, features, bg, offsets, ids, trans, n_contrib,
            torch.randn(H, W, 3, dtype=torch.float64), torch.randn(H, W, dtype=torch.float64))
    torch.library.opcheck(torch.ops.cobgs.blend_bwd.default, args)


def test_gradcheck_project():
    means, quats, scales, _, _, viewmat, K = small_scene(n=5)

    def fn(means, quats, scales):
        m2, conics, depths, _ = ops.project(means, quats, scales, viewmat, K, W, H)
        return m2, conics, depths

    inputs = tuple(t.clone().requires_grad_() for t in (means, quats, scales))
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-7, rtol=1e-5)


def test_gradcheck_project_through_the_jacobian_clamp():
    """Gaussians beyond 1.3x the half field of view: the clamped Jacobian's gradient."""
    means, quats, scales, _, _, viewmat, K = small_scene(n=4)
    means = means.clone()
    means[:, 0] = torch.tensor([1.4, -1.5, 1.45, -1.6], dtype=torch.float64) * (W / 2 / 18.0) \
        * means[:, 2]
    scales = scales * 4  # large enough to stay on screen (not culled) despite the offset

    def fn(means, quats, scales):
        m2, conics, _, radii = ops.project(means, quats, scales, viewmat, K, W, H)
        assert (radii > 0).all()
        return m2, conics

    inputs = tuple(t.clone().requires_grad_() for t in (means, quats, scales))
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-7, rtol=1e-5)


def test_gradcheck_blend():
    m2, conics, _, _, opacities, features, offsets, ids = projected()
    bg = torch.rand(3, dtype=torch.float64)
    proj = torch.randn(20, H * W * 4, dtype=torch.float64,
                       generator=torch.Generator().manual_seed(1))

    def fn(m2, conics, opacities, features, bg):
        image, trans, *_ = ops.blend(m2, conics, opacities, features, bg, offsets, ids, W, H)
        # 20 random linear combinations of all outputs (see test_rasterize's gradcheck).
        return proj @ torch.cat([image.flatten(), trans.flatten()])

    inputs = tuple(t.clone().requires_grad_() for t in (m2, conics, opacities, features, bg))
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_ops_match_reference_functions():
    """Each native op against the reference function it mirrors (float64)."""
    means, quats, scales, opacities, features, viewmat, K = small_scene(n=30)
    nat = ops.project(means, quats, scales, viewmat, K, W, H)
    rf = ref.project_reference(means, quats, scales, viewmat, K, W, H)
    for a, b in zip(nat, rf):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    m2, conics, depths, radii = nat
    offsets, ids = ops.bin_tiles(m2, radii, depths, W, H)
    r_off, r_ids = ref.bin_tiles_reference(m2, radii, depths, W, H)
    assert torch.equal(offsets, r_off) and torch.equal(ids, r_ids)
    bg = torch.rand(3, dtype=torch.float64)
    image, trans, n_contrib, _, _ = ops.blend(m2, conics, opacities, features, bg, offsets,
                                               ids, W, H)
    r_image, r_trans, _, _ = ref.blend_reference(m2, conics, opacities, features, bg, offsets,
                                                 ids, W, H)
    torch.testing.assert_close(image, r_image, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(trans, r_trans, rtol=1e-12, atol=1e-12)
    assert n_contrib.max() > 0 and n_contrib.dtype == torch.int32


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_bin_tiles_depth_sort_on_many_gaussians(dtype):
    """Enough Gaussians that the depth sort splits its passes between threads: the lists
    equal the reference's stable sorts (ties in index order) for 1, 2 and 3 threads.
    Depths span several octaves (every key byte varies) and repeat (ties)."""
    g = torch.Generator().manual_seed(11)
    n = 60_000
    m2 = (torch.rand(n, 2, generator=g, dtype=torch.float64) * torch.tensor([360.0, 260.0])
          - 20).to(dtype)
    depths = torch.exp(torch.rand(n, generator=g, dtype=torch.float64) * 12 - 4).to(dtype)
    depths[::3] = depths[7::3].repeat(2)[: len(depths[::3])]  # many exact ties
    depths[5::101] = 1.0
    radii = (torch.rand(n, generator=g) * 12).int()
    radii[::13] = 0
    r_off, r_ids = ref.bin_tiles_reference(m2, radii, depths, 320, 240)
    before = torch.get_num_threads()
    try:
        for threads in (1, 2, 3):
            torch.set_num_threads(threads)
            off, ids = ops.bin_tiles(m2, radii, depths, 320, 240)
            assert torch.equal(off, r_off) and torch.equal(ids, r_ids), threads
    finally:
        torch.set_num_threads(before)


def test_bin_tiles_names_the_first_bad_depth():
    """A visible Gaussian with a depth <= 0 or NaN is an error naming the first such index
    (index order, whichever thread's range it falls in); culled ones are not checked."""
    g = torch.Generator().manual_seed(12)
    n = 30_000
    m2 = torch.rand(n, 2, generator=g) * 300
    depths = torch.rand(n, generator=g) + 0.5
    radii = torch.full((n,), 3, dtype=torch.int32)
    depths[100] = -1.0
    radii[100] = 0  # culled: ignored
    depths[20_001] = float("nan")
    depths[25_000] = 0.0
    with pytest.raises(RuntimeError, match=r"depths\[20001\] of a visible Gaussian must be "
                                           r"positive and finite"):
        ops.bin_tiles(m2, radii, depths, 320, 240)
    depths[20_001] = 1.0
    with pytest.raises(RuntimeError, match=r"depths\[25000\]"):
        torch.ops.cobgs.bin_tiles_tight(m2, radii, depths, torch.tensor([[0.5, 0.0, 0.5]]).expand(n, 3).contiguous(),
                                        torch.full((n,), 0.5), 320, 240)


def test_thread_count_does_not_change_results():
    """Per-entry gradient slots reduced in list order: bitwise identical for 1 or 2 threads."""
    m2, conics, _, _, opacities, features, offsets, ids = projected(torch.float32)
    bg = torch.rand(3)
    before = torch.get_num_threads()
    results = []
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            out = ops.blend(m2, conics, opacities, features, bg, offsets, ids, W, H)
            g = torch.ops.cobgs.blend_bwd(m2, conics, opacities, features, bg, offsets, ids,
                                          out[1], out[2], torch.ones(H, W, 3), torch.ones(H, W))
            results.append((out[0], *g))
    finally:
        torch.set_num_threads(before)
    for a, b in zip(*results):
        assert torch.equal(a, b)


def test_simd_dispatch_is_bitwise_identical(tmp_path):
    """The AVX2 kernels (picked at run time on x86-64 CPUs that have it) and the baseline
    kernels (forced by COBGS_DISABLE_AVX2=1) give bit-identical results: only exactly
    rounded operations, no fused multiply-add (-ffp-contract=off), fixed summation order.
    On a CPU without AVX2 both runs take the baseline path."""
    import subprocess
    import sys
    from pathlib import Path

    code = f"""
import sys, torch
sys.path.insert(0, {str(Path(__file__).parent)!r})
from test_ops import projected, W, H, _hard_projection_inputs
from cobgs.render import ops
m2, conics, _, _, opacities, features, offsets, ids = projected(torch.float32)
bg = torch.full((3,), 0.25)
labels = torch.randint(-1, 3, (H, W), generator=torch.Generator().manual_seed(0),
                       dtype=torch.int32)
out = ops.blend(m2, conics, opacities, features, bg, offsets, ids, W, H, labels, 3)
g = torch.Generator().manual_seed(1)
grads = torch.ops.cobgs.blend_bwd(m2, conics, opacities, features, bg, offsets, ids, out[1],
                                  out[2], torch.randn(H, W, 3, generator=g),
                                  torch.randn(H, W, generator=g))
pm, pq, ps, vm, KK = _hard_projection_inputs(torch.float32)
proj = torch.ops.cobgs.project(pm, pq, ps, vm, KK, 320, 240, 0.01)
v = [torch.randn(t.shape, generator=g) for t in proj[:3]]
pgrads = torch.ops.cobgs.project_bwd(pm, pq, ps, vm, KK, 320, 240, proj[3], *v)
tight = torch.ops.cobgs.bin_tiles_tight(proj[0], proj[3], proj[2], proj[1],
                                        torch.rand(len(pm), generator=g), 320, 240)
shN = torch.randn(len(pm), 15, 3, generator=g) * 0.3
col = torch.ops.cobgs.sh_colors(pm, torch.randn(len(pm), 1, 3, generator=g), shN,
                                torch.zeros(3), 3)
shg = torch.ops.cobgs.sh_colors_bwd(pm, torch.randn(len(pm), 1, 3, generator=g), shN,
                                    torch.zeros(3), 3, torch.randn(col.shape, generator=g))
from cobgs.evaluate.ssim import gauss_1d
blurs = []
for dt in (torch.float32, torch.float64):  # widths: lane blocks plus a tail, and under 8
    for shape in ((2, 3, 29, 37), (1, 2, 13, 5)):
        xs = torch.rand(shape, generator=g, dtype=dt)
        ys = torch.rand(shape, generator=g, dtype=dt)
        w = gauss_1d(11, 1.5, dt, "cpu")
        blurs += [*torch.ops.cobgs.ssim_mean_grad(xs, ys, w), torch.ops.cobgs.gauss_blur(xs, w),
                  *torch.ops.cobgs.photometric_loss_grad(xs.permute(0, 2, 3, 1).contiguous(),
                                                         ys.permute(0, 2, 3, 1).contiguous(), w,
                                                         0.2)]
torch.save([*out, *grads, *proj, *pgrads, *tight, col, *shg, *blurs], sys.argv[1])
"""
    results = []
    for disable in ("1", "0"):
        path = tmp_path / f"out{disable}.pt"
        env = dict(__import__("os").environ, COBGS_DISABLE_AVX2=disable)
        proc = subprocess.run([sys.executable, "-c", code, str(path)], env=env,
                              capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr
        results.append(torch.load(path))
    assert results[0][3].sum() > 0  # label counts exercised
    for a, b in zip(*results):
        assert torch.equal(a, b)


def _hard_projection_inputs(dtype, n=203):
    """Gaussians that take every branch of the projection: ordinary, behind the camera, at
    the near plane, far off-screen (clamped Jacobian), zero quaternion, overflowing and
    zero scales."""
    g = torch.Generator().manual_seed(3)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * 2
    means[:, 2] += 4.0
    means[::9] *= 1e3
    means[1::11, 2] = 0.01
    means[2::13, 2] = -1.0
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    quats[3::17] = 0
    scales = torch.exp(torch.randn(n, 3, generator=g, dtype=dtype) - 3)
    scales[4::19] = 1e30
    scales[5::23] = 0
    viewmat = torch.eye(4, dtype=dtype)
    viewmat[:3, 3] = torch.tensor([0.1, -0.2, 0.3], dtype=dtype)
    K = torch.tensor([[300.0, 0, 160], [0, 310.0, 120], [0, 0, 1]], dtype=dtype)
    return means, quats, scales, viewmat, K


def test_project_lanes_match_one_at_a_time():
    """float32 projects 8 Gaussians at a time in lane vectors and the remainder one by one
    through the same formulas: every lane must be bitwise what the one-Gaussian path gives
    (each Gaussian alone runs the scalar path), forward and backward, culled or not."""
    means, quats, scales, viewmat, K = _hard_projection_inputs(torch.float32)
    n = means.shape[0]
    outs = torch.ops.cobgs.project(means, quats, scales, viewmat, K, 320, 240, 0.01)
    assert 0 < int((outs[3] > 0).sum()) < n  # some culled, some visible
    g = torch.Generator().manual_seed(4)
    v = [torch.randn(t.shape, generator=g) for t in outs[:3]]
    v[0][::7] = 0
    v[1][::7] = 0
    v[2][::7] = 0  # no gradient at all: skipped
    grads = torch.ops.cobgs.project_bwd(means, quats, scales, viewmat, K, 320, 240, outs[3], *v)
    for i in range(n):
        sl = slice(i, i + 1)
        one = torch.ops.cobgs.project(means[sl], quats[sl], scales[sl], viewmat, K, 320, 240,
                                      0.01)
        for a, b in zip(outs, one):
            assert torch.equal(a[sl], b), i
        one_g = torch.ops.cobgs.project_bwd(means[sl], quats[sl], scales[sl], viewmat, K, 320,
                                            240, one[3], *(t[sl] for t in v))
        for a, b in zip(grads, one_g):
            assert torch.equal(a[sl], b), i
    assert all(bool(t.isfinite().all()) for t in grads)
