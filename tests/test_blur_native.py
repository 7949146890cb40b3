"""The native ``cobgs::gauss_blur`` (the SSIM blur on the CPU) against the grouped 1D
``conv2d`` of :func:`cobgs.losses._blur` it replaces.

Tolerances: each output is a sum of n² = 121 products of a kernel weight and an input
value, in a different order than oneDNN's; float64 agrees to 1e-12 of the largest value,
float32 to 1e-6 of it.
"""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from cobgs import _ops
from cobgs.losses import _gauss_1d


@pytest.fixture(scope="module", autouse=True)
def _loaded():
    _ops.ensure_loaded()


def conv_blur(t, g):
    k, n = t.shape[1], g.shape[0]
    pad = n // 2
    t = F.conv2d(t, g.view(1, 1, n, 1).expand(k, 1, n, 1), padding=(pad, 0), groups=k)
    return F.conv2d(t, g.view(1, 1, 1, n).expand(k, 1, 1, n), padding=(0, pad), groups=k)


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 1e-6)])
@pytest.mark.parametrize("shape", [(1, 15, 37, 53), (2, 3, 5, 4), (1, 1, 1, 30)])
def test_matches_conv2d(dtype, tol, shape):
    x = torch.rand(shape, generator=torch.Generator().manual_seed(0), dtype=dtype)
    g = _gauss_1d(11, 1.5, dtype, "cpu")
    nat = _ops.gauss_blur(x, g)
    ref = conv_blur(x, g)
    torch.testing.assert_close(nat, ref, rtol=0, atol=tol * ref.abs().max().item())
    # An asymmetric kernel: a cross-correlation, as conv2d.
    h = torch.arange(1.0, 6.0, dtype=dtype)
    torch.testing.assert_close(_ops.gauss_blur(x, h), conv_blur(x, h), rtol=0,
                               atol=tol * 50 * x.abs().max().item())


def test_opcheck_and_errors():
    x = torch.rand(1, 2, 6, 7, dtype=torch.float64)
    g = _gauss_1d(3, 1.0, torch.float64, "cpu")
    torch.library.opcheck(torch.ops.cobgs.gauss_blur, (x, g))
    with pytest.raises(RuntimeError, match="odd length"):
        torch.ops.cobgs.gauss_blur(x, torch.ones(4, dtype=torch.float64))
    with pytest.raises(RuntimeError, match="x must have shape"):
        torch.ops.cobgs.gauss_blur(x[0], g)


def test_ssim_loss_uses_it_and_agrees():
    from cobgs.losses import ssim, ssim_map

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
    from cobgs.losses import SSIM_SIGMA, SSIM_WINDOW, _MeanSSIM

    g = torch.Generator().manual_seed(4)
    x = torch.rand(2, 3, 23, 31, generator=g, dtype=torch.float64).to(dtype)  # batch of 2
    y = torch.rand(2, 3, 23, 31, generator=g, dtype=torch.float64).to(dtype)
    w = _gauss_1d(SSIM_WINDOW, SSIM_SIGMA, dtype, "cpu")
    mean, grad = _ops.ssim_mean_grad(x, y, w)
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
    w = _gauss_1d(11, 1.5, dtype, "cpu")
    before = torch.get_num_threads()
    try:
        outs = []
        for threads in (1, 2, 3):
            torch.set_num_threads(threads)
            outs.append(_ops.ssim_mean_grad(x, y, w))
    finally:
        torch.set_num_threads(before)
    for mean, grad in outs[1:]:
        assert torch.equal(mean, outs[0][0])
        assert torch.equal(grad, outs[0][1])


def test_fused_ssim_opcheck_and_errors():
    x = torch.rand(1, 3, 9, 11, dtype=torch.float64)
    y = torch.rand(1, 3, 9, 11, dtype=torch.float64)
    w = _gauss_1d(5, 1.0, torch.float64, "cpu")
    torch.library.opcheck(torch.ops.cobgs.ssim_mean_grad, (x, y, w))
    with pytest.raises(RuntimeError, match="y must have the shape of x"):
        torch.ops.cobgs.ssim_mean_grad(x, y[:, :2], w)
    with pytest.raises(RuntimeError, match="x must have shape"):
        torch.ops.cobgs.ssim_mean_grad(x[0], y[0], w)
    with pytest.raises(RuntimeError, match="odd length"):
        torch.ops.cobgs.ssim_mean_grad(x, y, torch.ones(4, dtype=torch.float64))
