"""Spherical harmonics against an independent closed form (associated Legendre functions)."""

import math

import numpy as np
import pytest
import torch
from scipy.special import lpmv

from cobgs.errors import InputError
from cobgs.gaussians.sh import eval_sh, num_coeffs, rgb_to_sh0, sh0_to_rgb, sh_basis, sh_to_color


def real_sh_closed_form(l: int, m: int, dirs: np.ndarray) -> np.ndarray:
    """Orthonormal real SH with the Condon–Shortley phase (scipy's lpmv includes it)."""
    x, y, z = dirs[:, 0], dirs[:, 1], dirs[:, 2]
    theta = np.arccos(np.clip(z, -1, 1))
    phi = np.arctan2(y, x)
    am = abs(m)
    k = math.sqrt((2 * l + 1) / (4 * math.pi) * math.factorial(l - am) / math.factorial(l + am))
    p = lpmv(am, l, np.cos(theta))
    if m == 0:
        return k * p
    if m > 0:
        return math.sqrt(2) * k * np.cos(m * phi) * p
    return math.sqrt(2) * k * np.sin(am * phi) * p


@pytest.fixture
def dirs():
    g = torch.Generator().manual_seed(0)
    d = torch.randn(500, 3, generator=g, dtype=torch.float64)
    return d / d.norm(dim=1, keepdim=True)


def test_basis_matches_closed_form(dirs):
    basis = sh_basis(3, dirs).numpy()
    assert basis.shape == (500, 16)
    for l in range(4):
        for m in range(-l, l + 1):
            ref = real_sh_closed_form(l, m, dirs.numpy())
            np.testing.assert_allclose(basis[:, l * l + l + m], ref, rtol=1e-10, atol=1e-12)


def test_basis_is_orthonormal_on_sphere():
    # Monte Carlo over many directions: E[Y_i Y_j] = δ_ij / (4π).
    g = torch.Generator().manual_seed(1)
    d = torch.randn(400_000, 3, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=1, keepdim=True)
    b = sh_basis(3, d)
    gram = (b.T @ b / d.shape[0] * 4 * math.pi).numpy()
    np.testing.assert_allclose(gram, np.eye(16), atol=0.02)


def test_eval_sh_degree_truncation_and_colour(dirs):
    g = torch.Generator().manual_seed(2)
    coeffs = torch.randn(500, 16, 3, generator=g, dtype=torch.float64)
    for deg in range(4):
        k = num_coeffs(deg)
        ref = (sh_basis(deg, dirs)[..., None] * coeffs[:, :k]).sum(1)
        assert torch.allclose(eval_sh(deg, coeffs, dirs), ref)
    col = sh_to_color(3, coeffs, dirs)
    assert torch.all(col >= 0)
    rgb = torch.tensor([[0.2, 0.5, 0.9]])
    assert torch.allclose(sh0_to_rgb(rgb_to_sh0(rgb)), rgb)
    # Degree 0: the colour is view independent and equals sh0_to_rgb.
    c0 = rgb_to_sh0(rgb)[:, None, :].expand(500, 1, 3).double()
    assert torch.allclose(sh_to_color(0, c0, dirs), rgb.double().expand(500, 3))


def test_errors():
    with pytest.raises(InputError, match="degree"):
        sh_basis(4, torch.zeros(1, 3))
    with pytest.raises(InputError, match="coefficients"):
        eval_sh(2, torch.zeros(3, 4, 3), torch.zeros(3, 3))
