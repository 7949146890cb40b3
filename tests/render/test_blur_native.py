"""The native ``cobgs::gauss_blur`` (the SSIM blur on the CPU) against the grouped 1D
``conv2d`` of :func:`cobgs.evaluate.ssim._blur` it replaces.

Tolerances: each output is a sum of n² = 121 products of a kernel weight and an input
value, in a different order than oneDNN's; float64 agrees to 1e-12 of the largest value,
float32 to 1e-6 of it.
"""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from cobgs.render import ops
from cobgs.evaluate.ssim import gauss_1d


@pytest.fixture(scope="module", autouse=True)
def _loaded():
    ops.ensure_loaded()


def conv_blur(t, g):
    k, n = t.shape[1], g.shape[0]
    pad = n // 2
    t = F.conv2d(t, g.view(1, 1, n, 1).expand(k, 1, n, 1), padding=(pad, 0), groups=k)
    return F.conv2d(t, g.view(1, 1, 1, n).expand(k, 1, 1, n), padding=(0, pad), groups=k)


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 1e-6)])
@pytest.mark.parametrize("shape", [(1, 15, 37, 53), (2, 3, 5, 4), (1, 1, 1, 30)])
def test_matches_conv2d(dtype, tol, shape):
    x = torch.rand(shape, generator=torch.Generator().manual_seed(0), dtype=dtype)
    g = gauss_1d(11, 1.5, dtype, "cpu")
    nat = ops.gauss_blur(x, g)
    ref = conv_blur(x, g)
    torch.testing.assert_close(nat, ref, rtol=0, atol=tol * ref.abs().max().item())
    # An asymmetric kernel: a cross-correlation, as conv2d.
    h = torch.arange(1.0, 6.0, dtype=dtype)
    torch.testing.assert_close(ops.gauss_blur(x, h), conv_blur(x, h), rtol=0,
                               atol=tol * 50 * x.abs().max().item())


def test_opcheck_and_errors():
    x = torch.rand(1, 2, 6, 7, dtype=torch.float64)
    g = gauss_1d(3, 1.0, torch.float64, "cpu")
    torch.library.opcheck(torch.ops.cobgs.gauss_blur, (x, g))
    with pytest.raises(RuntimeError, match="odd length"):
        torch.ops.cobgs.gauss_blur(x, torch.ones(4, dtype=torch.float64))
    with pytest.raises(RuntimeError, match="x must have shape"):
        torch.ops.cobgs.gauss_blur(x[0], g)


def test_ssim_loss_uses_it_and_agrees():
    from cobgs.evaluate.ssim import ssim, ssim_map

    g = torch.Generator().manual_seed(3)
    img = torch.rand(40, 50, 3, generator=g, requires_grad=True)
    ref = torch.rand(40, 50, 3, generator=g)
    fast = ssim(img, ref)  # analytic backward: blurs without autograd -> native
    fast.backward()
    slow_img = img.detach().clone().requires_grad_()
    slow = ssim_map(slow_img, ref).mean()  # autograd through conv2d
    slow.backward()
    torch.testing.assert_close(fast, slow, rtol=0, atol=1e-6)
    torch.testing.assert_close(img.grad, slow_img.grad, rtol=0,
                               atol=1e-6 * slow_img.grad.abs().max().item())


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 2e-6)])
def test_fused_ssim_op_matches_the_python_analytic_path(dtype, tol):
    from cobgs.evaluate.ssim import SSIM_SIGMA, SSIM_WINDOW, _MeanSSIM

    g = torch.Generator().manual_seed(4)
    x = torch.rand(2, 3, 23, 31, generator=g, dtype=torch.float64).to(dtype)  # batch of 2
    y = torch.rand(2, 3, 23, 31, generator=g, dtype=torch.float64).to(dtype)
    w = gauss_1d(SSIM_WINDOW, SSIM_SIGMA, dtype, "cpu")
    mean, grad = ops.ssim_mean_grad(x, y, w)
    xr = x.clone().requires_grad_()
    ref = _MeanSSIM.apply(xr, y, w)  # the pure-PyTorch analytic forward and backward
    ref.backward()
    torch.testing.assert_close(mean, ref.detach(), rtol=0, atol=tol)
    torch.testing.assert_close(grad, xr.grad, rtol=0, atol=tol * 10 * xr.grad.abs().max().item())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fused_ssim_op_does_not_depend_on_the_thread_count(dtype):
    """Rows are shared out between threads, but every output and the mean (summed per row,
    then over rows in order) are the same bits whatever the thread count."""
    g = torch.Generator().manual_seed(5)
    x = torch.rand(2, 3, 41, 45, generator=g, dtype=dtype)
    y = (x + 0.1 * torch.randn(x.shape, generator=g, dtype=dtype)).clamp(0, 1)
    w = gauss_1d(11, 1.5, dtype, "cpu")
    before = torch.get_num_threads()
    try:
        outs = []
        for threads in (1, 2, 3):
            torch.set_num_threads(threads)
            outs.append(ops.ssim_mean_grad(x, y, w))
    finally:
        torch.set_num_threads(before)
    for mean, grad in outs[1:]:
        assert torch.equal(mean, outs[0][0])
        assert torch.equal(grad, outs[0][1])


def test_fused_ssim_opcheck_and_errors():
    x = torch.rand(1, 3, 9, 11, dtype=torch.float64)
    y = torch.rand(1, 3, 9, 11, dtype=torch.float64)
    w = gauss_1d(5, 1.0, torch.float64, "cpu")
    torch.library.opcheck(torch.ops.cobgs.ssim_mean_grad, (x, y, w))
    with pytest.raises(RuntimeError, match="y must have the shape of x"):
        torch.ops.cobgs.ssim_mean_grad(x, y[:, :2], w)
    with pytest.raises(RuntimeError, match="x must have shape"):
        torch.ops.cobgs.ssim_mean_grad(x[0], y[0], w)
    with pytest.raises(RuntimeError, match="odd length"):
        torch.ops.cobgs.ssim_mean_grad(x, y, torch.ones(4, dtype=torch.float64))


def _photometric_reference(img, ref, lam):
    """The loss on plain autograd: L1 and SSIM through conv2d (cobgs.evaluate.ssim.ssim_map)."""
    from cobgs.evaluate.ssim import ssim_map
    from cobgs.train.losses import l1_loss

    x = img.detach().clone().requires_grad_()
    loss = (1 - lam) * l1_loss(x, ref) + lam * (1 - ssim_map(x, ref).mean())
    loss.backward()
    return loss.detach(), x.grad


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 2e-6)])
@pytest.mark.parametrize("shape", [(37, 45, 3), (2, 20, 13, 1), (1, 9, 5, 2)])
@pytest.mark.parametrize("lam", [0.2, 0.0, 1.0])
def test_fused_photometric_loss_matches_autograd(dtype, tol, shape, lam):
    """cobgs::photometric_loss_grad on channel-last images (widths with and without a lane
    tail, one or several channels, a batch) against L1 + SSIM on autograd; pixels where
    img == ref exactly get the L1 subgradient 0, as autograd's."""
    from cobgs.evaluate.ssim import SSIM_SIGMA, SSIM_WINDOW

    g = torch.Generator().manual_seed(6)
    img = torch.rand(shape, generator=g, dtype=torch.float64).to(dtype)
    ref = torch.rand(shape, generator=g, dtype=torch.float64).to(dtype)
    ref.view(-1)[::5] = img.view(-1)[::5]
    w = gauss_1d(SSIM_WINDOW, SSIM_SIGMA, dtype, "cpu")
    l1, s, grad = ops.photometric_loss_grad(img, ref, w, lam)
    loss, ref_grad = _photometric_reference(img, ref, lam)
    torch.testing.assert_close((1 - lam) * l1 + lam * (1 - s), loss, rtol=0, atol=tol)
    torch.testing.assert_close(l1, (img - ref).abs().mean(), rtol=0, atol=tol)
    torch.testing.assert_close(grad, ref_grad, rtol=0,
                               atol=tol * 10 * ref_grad.abs().max().item())


def test_fused_photometric_ssim_part_is_the_planar_ops_bit_for_bit():
    """Blurring channel-interleaved rows (taps C apart) gives the same bits as blurring each
    channel plane: with λ = 1 the gradient is exactly minus ssim_mean_grad's."""
    g = torch.Generator().manual_seed(7)
    img = torch.rand(2, 29, 35, 3, generator=g)
    ref = torch.rand(2, 29, 35, 3, generator=g)
    w = gauss_1d(11, 1.5, torch.float32, "cpu")
    _, s, grad = ops.photometric_loss_grad(img, ref, w, 1.0)
    mean, planar = ops.ssim_mean_grad(img.permute(0, 3, 1, 2).contiguous(),
                                       ref.permute(0, 3, 1, 2).contiguous(), w)
    assert torch.equal(grad, -planar.permute(0, 2, 3, 1))
    torch.testing.assert_close(s, mean, rtol=0, atol=1e-6)


def test_fused_photometric_does_not_depend_on_the_thread_count():
    g = torch.Generator().manual_seed(8)
    img = torch.rand(53, 61, 3, generator=g)
    ref = torch.rand(53, 61, 3, generator=g)
    w = gauss_1d(11, 1.5, torch.float32, "cpu")
    before = torch.get_num_threads()
    try:
        outs = []
        for threads in (1, 2, 3):
            torch.set_num_threads(threads)
            outs.append(ops.photometric_loss_grad(img, ref, w, 0.2))
    finally:
        torch.set_num_threads(before)
    for out in outs[1:]:
        assert all(torch.equal(a, b) for a, b in zip(out, outs[0]))


def test_photometric_loss_takes_the_fused_path_and_agrees():
    from cobgs.evaluate.ssim import ssim
    from cobgs.train.losses import l1_loss, photometric_loss

    g = torch.Generator().manual_seed(9)
    img = torch.rand(30, 41, 3, generator=g, requires_grad=True)
    ref = torch.rand(30, 41, 3, generator=g)
    fused = photometric_loss(img, ref, 0.2)
    assert type(fused.grad_fn).__name__.startswith("_NativePhotometricLoss")
    (2.0 * fused).backward()  # the upstream gradient scales the saved one
    x = img.detach().clone().requires_grad_()
    plain = 0.8 * l1_loss(x, ref) + 0.2 * (1 - ssim(x, ref))
    (2.0 * plain).backward()
    torch.testing.assert_close(fused, plain, rtol=0, atol=1e-6)
    torch.testing.assert_close(img.grad, x.grad, rtol=0, atol=1e-6 * x.grad.abs().max().item())
    # ref needing a gradient, or no gradient at all: the plain path.
    assert photometric_loss(img.detach(), ref).grad_fn is None


def test_fused_photometric_opcheck_and_errors():
    img = torch.rand(9, 11, 3, dtype=torch.float64)
    ref = torch.rand(9, 11, 3, dtype=torch.float64)
    w = gauss_1d(5, 1.0, torch.float64, "cpu")
    torch.library.opcheck(torch.ops.cobgs.photometric_loss_grad, (img, ref, w, 0.2))
    with pytest.raises(RuntimeError, match="ref must have the shape of img"):
        torch.ops.cobgs.photometric_loss_grad(img, ref[:, :5].contiguous(), w, 0.2)
    with pytest.raises(RuntimeError, match=r"img must have shape \[H, W, C\]"):
        torch.ops.cobgs.photometric_loss_grad(img[0], ref[0], w, 0.2)
    with pytest.raises(RuntimeError, match="ssim_weight must be in"):
        torch.ops.cobgs.photometric_loss_grad(img, ref, w, 1.5)
    with pytest.raises(RuntimeError, match="odd length"):
        torch.ops.cobgs.photometric_loss_grad(img, ref, torch.ones(4, dtype=torch.float64), 0.2)
