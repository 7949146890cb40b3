"""The native ``cobgs::sh_colors`` op (render's colour on the CPU) against the pure-PyTorch
SH colour of :meth:`cobgs.gaussians.model.GaussianModel.colors` / :func:`cobgs.gaussians.sh.sh_to_color`.

Float64 comparisons use rtol 1e-12: both sides evaluate the same polynomials with a few
dozen roundings each (the sums run in a different order). Float32 uses 1e-5 relative to
the largest colour for the same reason at single precision.
"""

from __future__ import annotations

import pytest
import torch

from cobgs.render import ops
from cobgs.gaussians.sh import num_coeffs, sh_to_color


@pytest.fixture(scope="module", autouse=True)
def _loaded():
    ops.ensure_loaded()


def sh_inputs(n=40, degree_max=3, dtype=torch.float64, seed=0, channels=3):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * 2
    sh0 = torch.randn(n, 1, channels, generator=g, dtype=dtype)
    shN = 0.5 * torch.randn(n, num_coeffs(degree_max) - 1, channels, generator=g, dtype=dtype)
    center = torch.tensor([0.3, -0.2, -4.0], dtype=dtype)
    return means, sh0, shN, center


def python_colors(means, sh0, shN, center, degree):
    """GaussianModel.colors, written out (the oracle)."""
    if degree == 0:
        return (sh0[:, 0, :] * 0.28209479177387814 + 0.5).clamp_min(0.0)
    k = num_coeffs(degree)
    coeffs = torch.cat([sh0, shN[:, : k - 1]], 1)
    dirs = means - center
    dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return sh_to_color(degree, coeffs, dirs)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_forward_and_gradients_match_python(degree):
    inputs = sh_inputs()
    nat_in = [t.clone().requires_grad_(i < 3) for i, t in enumerate(inputs)]
    ref_in = [t.clone().requires_grad_(i < 3) for i, t in enumerate(inputs)]
    nat = ops.sh_colors(*nat_in, degree)
    ref = python_colors(*ref_in, degree)
    assert (ref == 0).any() or degree == 0  # the clamp is exercised
    torch.testing.assert_close(nat, ref, rtol=1e-12, atol=1e-12)
    v = torch.randn(ref.shape, generator=torch.Generator().manual_seed(1), dtype=ref.dtype)
    (nat * v).sum().backward()
    (ref * v).sum().backward()
    for name, a, b in zip(("means", "sh0", "shN"), nat_in, ref_in):
        if b.grad is None:  # degree 0: neither means nor shN is read
            assert a.grad is None, name
            continue
        torch.testing.assert_close(a.grad, b.grad, rtol=1e-12, atol=1e-12,
                                   msg=lambda m: f"{name}: {m}")


def test_float32_and_other_channel_counts():
    means, sh0, shN, center = sh_inputs(n=300, dtype=torch.float32, channels=2)
    nat = ops.sh_colors(means, sh0, shN, center, 3)
    ref = python_colors(means.double(), sh0.double(), shN.double(), center.double(), 3)
    assert nat.dtype == torch.float32 and nat.shape == (300, 2)
    torch.testing.assert_close(nat.double(), ref, rtol=0, atol=1e-5 * ref.abs().max().item())


def test_gradcheck_and_opcheck():
    means, sh0, shN, center = sh_inputs(n=6)
    # Keep every colour away from the clamp's kink (finite differences straddle it).
    sh0 = sh0.abs() + 4.0
    inputs = (means.requires_grad_(), sh0.requires_grad_(), shN.requires_grad_())
    assert torch.autograd.gradcheck(
        lambda m, a, b: ops.sh_colors(m, a, b, center, 3), inputs, eps=1e-6, atol=1e-7,
        rtol=1e-5)
    torch.library.opcheck(torch.ops.cobgs.sh_colors,
                          (means.detach(), sh0.detach(), shN.detach(), center, 2))
    torch.library.opcheck(torch.ops.cobgs.sh_colors_bwd,
                          (means.detach(), sh0.detach(), shN.detach(), center, 3,
                           torch.ones(6, 3, dtype=torch.float64)))


def test_bad_inputs_name_the_tensor():
    means, sh0, shN, center = sh_inputs(n=4)
    with pytest.raises(RuntimeError, match="shN must have at least 15"):
        torch.ops.cobgs.sh_colors(means, sh0, shN[:, :3].contiguous(), center, 3)
    with pytest.raises(RuntimeError, match="center must have shape"):
        torch.ops.cobgs.sh_colors(means, sh0, shN, center[:2].contiguous(), 1)
    with pytest.raises(RuntimeError, match="degree must be in 0..3"):
        torch.ops.cobgs.sh_colors(means, sh0, shN, center, 4)


def test_render_uses_the_same_colours_as_the_model():
    from cobgs.render.camera import Camera  # noqa: F401  (render's camera type)
    from cobgs.gaussians.model import GaussianModel
    from cobgs.render.image import render

    means, sh0, shN, _ = sh_inputs(n=50, dtype=torch.float32)
    means[:, 2] = means[:, 2].abs() + 3.0
    model = GaussianModel(means=means, log_scales=torch.full((50, 3), -3.0),
                          quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(50, 1),
                          opacity_logits=torch.zeros(50), sh0=sh0, shN=shN)
    model.active_sh_degree = 3
    cam = _camera()
    nat = render(model, cam, backend="native").image
    py = render(model, cam, features=model.colors(cam.center)).image
    torch.testing.assert_close(nat, py, rtol=0, atol=1e-5)


def _camera():
    from cobgs.render.camera import Camera

    K = torch.tensor([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]])
    return Camera(K=K, viewmat=torch.eye(4), width=32, height=24)


def test_float32_rgb_lanes_match_one_at_a_time():
    """float32 RGB at degree 3 (the training case) runs 8 Gaussians at a time in lane
    vectors and the remainder one by one through the same formulas: every Gaussian must
    come out bitwise as when it is evaluated alone (one Gaussian takes the one-at-a-time
    path), colours and all three gradients, including Gaussians at the camera centre,
    clamped colours and Gaussians without any colour gradient."""
    n = 45  # 5 lane blocks and a remainder of 5
    means, sh0, shN, center = sh_inputs(n=n, dtype=torch.float32)
    means[::11] = center  # direction clamp
    colours = torch.ops.cobgs.sh_colors(means, sh0, shN, center, 3)
    assert (colours == 0).any() and (colours > 0).any()
    v = torch.randn(colours.shape, generator=torch.Generator().manual_seed(2))
    v[::4] = 0  # no gradient at all
    v[1::6, 1] = 0
    grads = torch.ops.cobgs.sh_colors_bwd(means, sh0, shN, center, 3, v)
    assert (grads[2][::4] == 0).all() and (grads[2][1] != 0).any()
    for i in range(n):
        sl = slice(i, i + 1)
        one = torch.ops.cobgs.sh_colors(means[sl], sh0[sl], shN[sl], center, 3)
        assert torch.equal(colours[sl], one), i
        one_g = torch.ops.cobgs.sh_colors_bwd(means[sl], sh0[sl], shN[sl], center, 3, v[sl])
        for a, b in zip(grads, one_g):
            assert torch.equal(a[sl], b) and torch.equal(a[sl].signbit(), b.signbit()), i
