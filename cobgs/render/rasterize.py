"""``cobgs.rasterize``: render 3D Gaussians into one camera (colour, alpha, label stats).

The contract (projection, culling, tiles, blending rule, pixel convention) is written out
in :mod:`cobgs.render.reference`, the pure-PyTorch oracle; the native backend (``csrc/``, built
on first use) computes the same numbers.
"""

from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor
from torch.utils.weak import WeakIdKeyDictionary

from cobgs.errors import InputError, check_shape
from cobgs.render.reference import RasterOutput, rasterize_reference

__all__ = ["rasterize"]

_FLOATS = (torch.float32, torch.float64)


def rasterize(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    scales: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    features: Tensor,  # [N, C]
    viewmat: Tensor,  # [4, 4]
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
    background: Optional[Tensor] = None,  # [C]
    pixel_labels: Optional[Tensor] = None,  # [H, W]
    num_labels: int = 2,
    *,
    backend: str = "native",
) -> RasterOutput:
    """Render N Gaussians with C feature channels into a ``height x width`` image.

    Follows standard 3DGS exactly (see :mod:`cobgs.render.reference` for every formula and
    cut-off): EWA projection with a 0.3 px² low-pass, 3-sigma radius, near plane 0.01,
    16x16 tiles in depth order, α = min(0.99, o·exp(power)), α < 1/255 skipped, a pixel
    stops before the Gaussian that would bring its transmittance below 1e-4.

    Args:
        means: Tensor  # [N, 3] world positions (float32 or float64; sets the dtype)
        quats: Tensor  # [N, 4] rotations (w, x, y, z), need not be normalised
        scales: Tensor  # [N, 3] linear (not log) standard deviations
        opacities: Tensor  # [N] in [0, 1] (after the sigmoid)
        features: Tensor  # [N, C] any C >= 1 channels (RGB, mask labels, ...)
        viewmat: Tensor  # [4, 4] world -> camera, OpenCV axes (+x right, +y down, +z fwd)
        K: Tensor  # [3, 3] pixel intrinsics [[fx, 0, cx], [0, fy, cy], [0, 0, 1]];
            pixel (i, j) is sampled at its centre (i + 0.5, j + 0.5)
        width, height: image size in pixels (>= 1)
        background: Tensor  # [C] colour behind everything; None = zeros
        pixel_labels: Tensor  # [H, W] integer labels 0..num_labels-1, -1 = ignore;
            when given, per-Gaussian label statistics are returned
        num_labels: K, the number of labels
        backend: "native" (C++ / CUDA ops: CPU, and CUDA devices when the extension was
            built with its CUDA kernels) or "reference" (pure PyTorch, any device)

    Returns:
        RasterOutput with ``image`` [H, W, C], ``alpha`` [H, W], ``transmittance``
        [H, W], ``radii`` [N] int32 (0 = culled), ``means2d`` [N, 2] (pixels),
        ``conics`` [N, 3], ``depths`` [N], and with ``pixel_labels``: ``label_counts``
        [N, K] int32 (pixels of each label the Gaussian contributes to, i.e. was blended
        into) and ``label_weights`` [N, K] float32 (Σ α·T over those pixels).

    Gradients flow to means, quats, scales, opacities, features and background (not to
    viewmat or K, not to the label statistics). For 3DGS densification call
    ``out.means2d.retain_grad()`` before ``backward()``: ``out.means2d.grad`` [N, 2] is
    dL/d(means2d) in *pixel* units. The original 3DGS accumulates the gradient w.r.t.
    NDC coordinates (its 2e-4 threshold is in those units); since ``x_pix = ((x_ndc + 1)
    W - 1) / 2``, the conversion is ``grad_ndc = grad_pix * (W / 2, H / 2)``, i.e.
    ``(out.means2d.grad * torch.tensor([W / 2, H / 2])).norm(dim=-1)``.

    Example: one Gaussian 2 units in front of a 32x24 pinhole camera (fx = fy = 40 px), 1 px
    wide on screen; the pixel next to its centre gets ``α = 0.9 · exp(-0.5 · 0.5 / 1.3)``
    (0.25 px² each way; 1 px² plus the 0.3 px² low-pass):

    >>> import torch, cobgs
    >>> K = torch.tensor([[40.0, 0.0, 16.0], [0.0, 40.0, 12.0], [0.0, 0.0, 1.0]])
    >>> out = cobgs.rasterize(torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
    ...                       torch.full((1, 3), 0.05), torch.tensor([0.9]), torch.tensor([[1.0, 0.5, 0.0]]),
    ...                       torch.eye(4), K, 32, 24)
    >>> out.image.shape, out.radii.tolist()
    (torch.Size([24, 32, 3]), [4])
    >>> round(float(out.alpha[12, 16]), 4), [round(float(c), 4) for c in out.image[12, 16]]
    (0.7425, [0.7425, 0.3713, 0.0])
    """
    _validate(means, quats, scales, opacities, features, viewmat, K, width, height,
              background, pixel_labels, num_labels, backend)
    viewmat = viewmat.to(means.dtype)
    K = K.to(means.dtype)
    if background is None:
        background = features.new_zeros(features.shape[1])
    if pixel_labels is not None:
        pixel_labels = pixel_labels.to(torch.int32)
    if backend == "reference":
        return rasterize_reference(means, quats, scales, opacities, features, viewmat, K,
                                   width, height, background, pixel_labels, num_labels)
    from cobgs.render import ops

    return ops.rasterize_native(means, quats, scales, opacities, features, viewmat, K,
                                 width, height, background, pixel_labels, num_labels)


def _validate(means, quats, scales, opacities, features, viewmat, K, width, height,
              background, pixel_labels, num_labels, backend) -> None:
    if backend not in ("native", "reference"):
        raise InputError(f'backend must be "native" or "reference", got {backend!r}')
    named = dict(means=means, quats=quats, scales=scales, opacities=opacities,
                 features=features, viewmat=viewmat, K=K)
    if background is not None:
        named["background"] = background
    if pixel_labels is not None:
        named["pixel_labels"] = pixel_labels
    for name, value in named.items():
        if not isinstance(value, Tensor):
            raise InputError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    for name, value in (("width", width), ("height", height), ("num_labels", num_labels)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise InputError(f"{name} must be a positive int, got {value!r}")

    if means.dtype not in _FLOATS:
        raise InputError(f"means must be float32 or float64, got {means.dtype}")
    check_shape("means", means, (None, 3))
    n = means.shape[0]
    if features.dim() != 2 or features.shape[0] != n or features.shape[1] < 1:
        raise InputError(f"features must have shape [N, C] with N = {n} (from means) and "
                         f"C >= 1, got {list(features.shape)}")
    c = features.shape[1]
    expected = dict(quats=(n, 4), scales=(n, 3), opacities=(n,), features=(n, c),
                    viewmat=(4, 4), K=(3, 3))
    if background is not None:
        expected["background"] = (c,)
    if pixel_labels is not None:
        expected["pixel_labels"] = (height, width)
    for name, shape in expected.items():
        value = named[name]
        if tuple(value.shape) != shape:
            raise InputError(f"{name} must have shape {list(shape)} (N = {n} from means, "
                             f"C = {c} from features, H x W = {height} x {width}), "
                             f"got {list(value.shape)}")
    for name, value in named.items():
        if value.device != means.device:
            raise InputError(f"{name} must be on {means.device} (the device of means), "
                             f"got {value.device}")
        if name in ("quats", "scales", "opacities", "features", "background") and \
                value.dtype != means.dtype:
            raise InputError(f"{name} must have dtype {means.dtype} (the dtype of means), "
                             f"got {value.dtype}")
        if name in ("viewmat", "K") and not value.dtype.is_floating_point:
            raise InputError(f"{name} must be a floating-point tensor, got {value.dtype}")
    if backend == "native" and means.device.type != "cpu":
        from cobgs.render import ops

        ops.check_serves(means.device)  # CUDA kernels built, or a clear error

    with torch.no_grad():
        if not _seen(("camera",), (viewmat, K)):
            check_camera(viewmat, K)
            _passed(("camera",), (viewmat, K))
        if pixel_labels is not None:
            if pixel_labels.dtype.is_floating_point or pixel_labels.dtype.is_complex or \
                    pixel_labels.dtype == torch.bool:
                raise InputError(f"pixel_labels must have an integer dtype, got "
                                 f"{pixel_labels.dtype}")
            if pixel_labels.numel() and not _seen(("labels", num_labels), (pixel_labels,)):
                lo, hi = (int(v) for v in torch.aminmax(pixel_labels))
                if lo < -1 or hi >= num_labels:
                    raise InputError(f"pixel_labels must lie in -1..{num_labels - 1} "
                                     f"(num_labels = {num_labels}), got values in {lo}..{hi}")
                _passed(("labels", num_labels), (pixel_labels,))


# Value checks of device tensors read their values back to the host (a synchronisation
# that stalls a GPU pipeline). Tensors that passed are remembered while they live and stay
# unchanged (same objects, same in-place version counters): a training loop renders the
# same cameras and label maps again and again. CPU tensors are always checked.
_PASSED = WeakIdKeyDictionary()


def _key(what: tuple, tensors: tuple) -> tuple:
    return what, tuple(id(t) for t in tensors[1:]), tuple(t._version for t in tensors)


def _seen(what: tuple, tensors: tuple) -> bool:
    """Whether these exact tensors, unchanged, passed the check ``what`` before."""
    if tensors[0].device.type == "cpu":
        return False
    entry = _PASSED.get(tensors[0])
    return entry is not None and entry[0] == _key(what, tensors)


def _passed(what: tuple, tensors: tuple) -> None:
    """Remember that the tensors passed ``what`` (one check remembered per tensor; the
    others are held, so that their ids stay theirs while the entry lives)."""
    if tensors[0].device.type != "cpu":
        _PASSED[tensors[0]] = (_key(what, tensors), tensors[1:])


def check_camera(viewmat: Tensor, K: Tensor) -> None:
    # One copy to the host for both.
    cam = torch.cat([viewmat[3].double(), K.double().flatten()]).cpu()
    last_row, k = cam[:4], cam[4:].reshape(3, 3)
    if not torch.equal(last_row, torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64)):
        raise InputError(f"viewmat must be a world->camera transform with last row "
                         f"[0, 0, 0, 1], got {last_row.tolist()}")
    if k[0, 1] != 0 or k[1, 0] != 0 or not torch.equal(
            k[2], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)):
        raise InputError(f"K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew), "
                         f"got {k.tolist()}")
    if not (k[0, 0] > 0 and k[1, 1] > 0):
        raise InputError(f"K must have positive focal lengths, got fx = {k[0, 0].item()}, "
                         f"fy = {k[1, 1].item()}")

