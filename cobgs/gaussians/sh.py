"""Real spherical harmonics up to degree 3, in the convention of 3DGS.

The basis is the orthonormal real SH with the Condon–Shortley phase, ordered by degree l
and then m = -l..l (so coefficient k = l² + l + m). Colour = Σ_k c_k Y_k(d) + 0.5,
clamped at 0, where d is the unit direction from the camera centre to the Gaussian.
The constants are the normalisation factors of each basis polynomial.
"""

from __future__ import annotations

import torch
from torch import Tensor

from cobgs.errors import InputError

C0 = 0.28209479177387814  # 1 / (2 sqrt(pi))
C1 = 0.4886025119029199  # sqrt(3 / (4 pi))
C2 = (
    1.0925484305920792,
    -1.0925484305920792,
    0.31539156525252005,
    -1.0925484305920792,
    0.5462742152960396,
)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)
MAX_DEGREE = 3


def num_coeffs(degree: int) -> int:
    """Number of SH coefficients per channel up to ``degree``: (degree + 1)²."""
    return (degree + 1) ** 2


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """Evaluate the real SH basis.

    Args:
        degree: 0..3.
        dirs: [..., 3] unit directions.

    Returns:
        [..., (degree + 1)²] basis values.
    """
    if not 0 <= degree <= MAX_DEGREE:
        raise InputError(f"SH degree must be in 0..{MAX_DEGREE}, got {degree}")
    if dirs.shape[-1] != 3:
        raise InputError(f"dirs must have shape [..., 3], got {list(dirs.shape)}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        out += [
            C2[0] * xy,
            C2[1] * yz,
            C2[2] * (2.0 * zz - xx - yy),
            C2[3] * xz,
            C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            C3[0] * y * (3.0 * xx - yy),
            C3[1] * xy * z,
            C3[2] * y * (4.0 * zz - xx - yy),
            C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            C3[4] * x * (4.0 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3.0 * yy),
        ]
    return torch.stack(out, -1)


def eval_sh(degree: int, coeffs: Tensor, dirs: Tensor) -> Tensor:
    """Σ_k coeffs[..., k, :] Y_k(dirs) over the first (degree + 1)² coefficients.

    Args:
        degree: active degree, 0..3 (coefficients beyond it are ignored).
        coeffs: [..., K, C] SH coefficients, K >= (degree + 1)².
        dirs: [..., 3] unit directions (broadcast against ``coeffs[..., 0, 0]``).

    Returns:
        [..., C] values (without the +0.5 offset; see :func:`sh_to_color`).
    """
    k = num_coeffs(degree)
    if coeffs.shape[-2] < k:
        raise InputError(
            f"coeffs must have at least {k} coefficients for degree {degree}, "
            f"got shape {list(coeffs.shape)}"
        )
    basis = sh_basis(degree, dirs)  # [..., k]
    return (basis.unsqueeze(-1) * coeffs[..., :k, :]).sum(-2)


def sh_to_color(degree: int, coeffs: Tensor, dirs: Tensor) -> Tensor:
    """3DGS colour: ``max(eval_sh + 0.5, 0)``; shapes as in :func:`eval_sh`."""
    return (eval_sh(degree, coeffs, dirs) + 0.5).clamp_min(0.0)


def rgb_to_sh0(rgb: Tensor) -> Tensor:
    """DC coefficient whose colour (degree 0) is ``rgb``: (rgb - 0.5) / C0."""
    return (rgb - 0.5) / C0


def sh0_to_rgb(sh0: Tensor) -> Tensor:
    """Inverse of :func:`rgb_to_sh0`."""
    return sh0 * C0 + 0.5

