"""Thin wrappers over ``torch.ops.cobgs.*``: loading, autograd and fake registration.

The C++ library (``csrc/``, built by :mod:`cobgs.render.build` on first use) defines the op
schemas and CPU kernels; this module adds what is registered from Python:

* autograd for ``project``, ``blend`` and ``sh_colors`` via
  ``torch.library.register_autograd``, whose backward calls the separate ``project_bwd`` /
  ``blend_bwd`` / ``sh_colors_bwd`` ops (no double backward);
* shape-only fake kernels for all ten ops via ``torch.library.register_fake``, so the
  ops work under FakeTensor / ``torch.compile`` (``bin_tiles`` has a data-dependent size).
"""

from __future__ import annotations

import contextlib
import threading
from typing import Optional, Tuple

import torch
from torch import Tensor

from cobgs.render import build
from cobgs.render.reference import NEAR_PLANE, TILE_SIZE, RasterOutput

_lock = threading.Lock()
_ready = False


def ensure_loaded() -> None:
    """Build/load the extension and register the Python side once per process."""
    global _ready
    if _ready:
        return
    with _lock:
        if _ready:
            return
        build.load_extension()
        _register()
        _ready = True


def _tiles(width: int, height: int) -> int:
    return ((width + TILE_SIZE - 1) // TILE_SIZE) * ((height + TILE_SIZE - 1) // TILE_SIZE)


def _register() -> None:
    lib = torch.library

    @lib.register_fake("cobgs::project")
    def _project_fake(means, quats, scales, viewmat, K, width, height, near_plane):
        n = means.shape[0]
        return (means.new_empty(n, 2), means.new_empty(n, 3), means.new_empty(n),
                means.new_empty(n, dtype=torch.int32))

    @lib.register_fake("cobgs::project_bwd")
    def _project_bwd_fake(means, quats, scales, viewmat, K, width, height, radii,
                          v_means2d, v_conics, v_depths):
        return torch.empty_like(means), torch.empty_like(quats), torch.empty_like(scales)

    @lib.register_fake("cobgs::bin_tiles")
    def _bin_tiles_fake(means2d, radii, depths, width, height):
        m = lib.get_ctx().new_dynamic_size()
        return (means2d.new_empty(_tiles(width, height) + 1, dtype=torch.int64),
                means2d.new_empty(m, dtype=torch.int32))

    @lib.register_fake("cobgs::bin_tiles_tight")
    def _bin_tiles_tight_fake(means2d, radii, depths, conics, opacities, width, height):
        m = lib.get_ctx().new_dynamic_size()
        record = 64 if means2d.dtype == torch.float32 else 80  # sizeof(GaussPrep<T>)
        return (means2d.new_empty(_tiles(width, height) + 1, dtype=torch.int64),
                means2d.new_empty(m, dtype=torch.int32),
                means2d.new_empty(means2d.shape[0], record, dtype=torch.uint8))

    @lib.register_fake("cobgs::blend")
    def _blend_fake(means2d, conics, opacities, features, background, tile_offsets,
                    flat_ids, width, height, pixel_labels, num_labels, prep=None, check=True):
        rows = means2d.shape[0] if pixel_labels is not None else 0
        return (features.new_empty(height, width, features.shape[1]),
                features.new_empty(height, width),
                features.new_empty(height, width, dtype=torch.int32),
                features.new_empty(rows, num_labels, dtype=torch.int32),
                features.new_empty(rows, num_labels, dtype=torch.float32))

    @lib.register_fake("cobgs::blend_bwd")
    def _blend_bwd_fake(means2d, conics, opacities, features, background, tile_offsets,
                        flat_ids, transmittance, n_contrib, v_image, v_transmittance,
                        prep=None, check=True):
        return (torch.empty_like(means2d), torch.empty_like(conics),
                torch.empty_like(opacities), torch.empty_like(features),
                torch.empty_like(background))

    def project_setup(ctx, inputs, output):
        means, quats, scales, viewmat, K, width, height, _near = inputs
        ctx.save_for_backward(means, quats, scales, viewmat, K, output[3])
        ctx.size = (width, height)

    def project_backward(ctx, v_means2d, v_conics, v_depths, _v_radii):
        if not any(ctx.needs_input_grad[:3]):  # e.g. only features/labels are trained
            return None, None, None, None, None, None, None, None
        means, quats, scales, viewmat, K, radii = ctx.saved_tensors
        v_means2d = _or_zeros(v_means2d, (means.shape[0], 2), means)
        v_conics = _or_zeros(v_conics, (means.shape[0], 3), means)
        v_depths = _or_zeros(v_depths, (means.shape[0],), means)
        v_means, v_quats, v_scales = torch.ops.cobgs.project_bwd(
            means, quats, scales, viewmat, K, *ctx.size, radii, v_means2d, v_conics, v_depths)
        return v_means, v_quats, v_scales, None, None, None, None, None

    lib.register_autograd("cobgs::project", project_backward, setup_context=project_setup)

    def blend_setup(ctx, inputs, output):
        (means2d, conics, opacities, features, background, tile_offsets, flat_ids,
         _w, _h, _labels, _k, *rest) = inputs
        prep = rest[0] if rest else None
        ctx.check = bool(rest[1]) if len(rest) > 1 else True
        ctx.has_prep = prep is not None
        ctx.save_for_backward(means2d, conics, opacities, features, background, tile_offsets,
                              flat_ids, output[1], output[2], *([prep] if ctx.has_prep else []))

    def blend_backward(ctx, v_image, v_trans, _v_nc, _v_counts, _v_weights):
        (means2d, conics, opacities, features, background, tile_offsets, flat_ids, trans,
         n_contrib, *rest) = ctx.saved_tensors
        prep = rest[0] if ctx.has_prep else None
        h, w = trans.shape
        v_image = _or_zeros(v_image, (h, w, features.shape[1]), features)
        v_trans = _or_zeros(v_trans, (h, w), features)
        grads = torch.ops.cobgs.blend_bwd(means2d, conics, opacities, features, background,
                                          tile_offsets, flat_ids, trans, n_contrib, v_image,
                                          v_trans, prep, ctx.check)
        return (*grads, None, None, None, None, None, None, None, None)

    lib.register_autograd("cobgs::blend", blend_backward, setup_context=blend_setup)

    @lib.register_fake("cobgs::sh_colors")
    def _sh_colors_fake(means, sh0, shN, center, degree):
        return means.new_empty(means.shape[0], sh0.shape[2])

    @lib.register_fake("cobgs::sh_colors_bwd")
    def _sh_colors_bwd_fake(means, sh0, shN, center, degree, v_colors):
        return torch.empty_like(means), torch.empty_like(sh0), torch.empty_like(shN)

    def sh_setup(ctx, inputs, output):
        means, sh0, shN, center, degree = inputs
        ctx.save_for_backward(means, sh0, shN, center)
        ctx.degree = degree

    def sh_backward(ctx, v_colors):
        means, sh0, shN, center = ctx.saved_tensors
        v_means, v_sh0, v_shN = torch.ops.cobgs.sh_colors_bwd(
            means, sh0, shN, center, ctx.degree, v_colors.contiguous())
        if ctx.degree == 0:
            # Degree 0 reads neither the means nor shN: no gradient at all (not zeros), as
            # the Python colour, so that Adam keeps no state for shN before it is used.
            v_means = v_shN = None
        return v_means, v_sh0, v_shN, None, None

    lib.register_autograd("cobgs::sh_colors", sh_backward, setup_context=sh_setup)

    @lib.register_fake("cobgs::gauss_blur")
    def _gauss_blur_fake(x, g):
        return torch.empty_like(x)

    @lib.register_fake("cobgs::ssim_mean_grad")
    def _ssim_mean_grad_fake(x, y, g):
        return x.new_empty(()), torch.empty_like(x)

    @lib.register_fake("cobgs::photometric_loss_grad")
    def _photometric_loss_grad_fake(img, ref, g, ssim_weight):
        return img.new_empty(()), img.new_empty(()), torch.empty_like(img)


def _or_zeros(grad: Optional[Tensor], shape, like: Tensor) -> Tensor:
    if grad is None:
        return like.new_zeros(shape)
    return grad.contiguous()


def project(means, quats, scales, viewmat, K, width: int, height: int,
            near_plane: float = NEAR_PLANE) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """Native ``cobgs::project`` (see :func:`cobgs.render.reference.project_reference`).

    Args:
        means [N, 3], quats [N, 4] (w, x, y, z), scales [N, 3] (linear), viewmat [4, 4]
        (world -> camera, OpenCV axes), K [3, 3]; width, height in pixels.

    Returns:
        means2d [N, 2] (pixels), conics [N, 3], depths [N], radii [N] int32 (0 = culled).
    """
    ensure_loaded()
    return torch.ops.cobgs.project(means.contiguous(), quats.contiguous(), scales.contiguous(),
                                   viewmat.contiguous(), K.contiguous(), width, height,
                                   near_plane)


def bin_tiles(means2d, radii, depths, width: int, height: int) -> Tuple[Tensor, Tensor]:
    """Native ``cobgs::bin_tiles`` (see :func:`cobgs.render.reference.bin_tiles_reference`).

    Args:
        means2d [N, 2], radii [N] int32, depths [N] (from :func:`project`).

    Returns:
        tile_offsets [T + 1] int32 (T = 16x16 tiles of the image), flat_ids [M] int32
        (the Gaussians of each tile, front to back).
    """
    ensure_loaded()
    return torch.ops.cobgs.bin_tiles(means2d.detach().contiguous(), radii.contiguous(),
                                     depths.detach().contiguous(), width, height)


def bin_tiles_tight(means2d, radii, depths, conics, opacities, width: int,
                    height: int) -> Tuple[Tensor, Tensor, Tensor]:
    """Native ``cobgs::bin_tiles_tight``: :func:`bin_tiles` lists without the entries that
    cannot reach α >= 1/255 anywhere in the tile (the blended pixels, their order, the
    image and the gradients are unchanged; ``n_contrib`` indexes the shorter lists), plus
    ``prep``, the per-Gaussian records :func:`blend` and the backward pass then reuse.

    Args:
        means2d [N, 2], radii [N] int32, depths [N], conics [N, 3], opacities [N].

    Returns:
        tile_offsets [T + 1] int32, flat_ids [M'] int32 (M' <= M of :func:`bin_tiles`),
        prep [N, P] (per-Gaussian records; P fixed by the op).
    """
    ensure_loaded()
    return torch.ops.cobgs.bin_tiles_tight(
        means2d.detach().contiguous(), radii.contiguous(), depths.detach().contiguous(),
        conics.detach().contiguous(), opacities.detach().contiguous(), width, height)


def blend(means2d, conics, opacities, features, background, tile_offsets, flat_ids,
          width: int, height: int, pixel_labels: Optional[Tensor] = None,
          num_labels: int = 2, prep: Optional[Tensor] = None, check: bool = True):
    """Native ``cobgs::blend`` (see :func:`cobgs.render.reference.blend_reference`).

    ``prep``: the third output of :func:`bin_tiles_tight` for the same means2d / conics /
    opacities (saves recomputing it in both passes), or None.
    ``check``: on CUDA, raise on bad tile lists / labels / n_contrib (the kernels find
    them; reading their verdict synchronises with the host). False for lists made by
    :func:`bin_tiles` (bad values are skipped, never dereferenced, either way).

    Args:
        means2d [N, 2], conics [N, 3], opacities [N], features [N, C], background [C],
        tile_offsets [T + 1] and flat_ids [M] (from :func:`bin_tiles` / :func:`bin_tiles_tight`),
        pixel_labels [H, W] int (−1 = ignore) or None, num_labels K.

    Returns image [H, W, C], transmittance [H, W], n_contrib [H, W] int32, label_counts
    [N, K] int32 and label_weights [N, K] float32 (both [0, K] without pixel_labels).
    """
    ensure_loaded()
    if pixel_labels is not None:
        pixel_labels = pixel_labels.to(torch.int32).contiguous()
    return torch.ops.cobgs.blend(means2d.contiguous(), conics.contiguous(),
                                 opacities.contiguous(), features.contiguous(),
                                 background.contiguous(), tile_offsets, flat_ids, width, height,
                                 pixel_labels, num_labels, prep, check)


def sh_colors(means, sh0, shN, center, degree: int) -> Tensor:
    """Native ``cobgs::sh_colors``: 3DGS view-dependent colour max(SH(d) + 0.5, 0).

    The same numbers as :meth:`cobgs.gaussians.model.GaussianModel.colors` (oracle: the
    pure-PyTorch :func:`cobgs.gaussians.sh.sh_to_color`), up to float rounding; gradients flow to
    means (through the direction), sh0 and shN.

    Args:
        means: [N, 3]; sh0: [N, 1, C]; shN: [N, M, C] with M >= (degree + 1)² - 1;
        center: [3] camera centre (converted to the dtype of means); degree: 0..3.

    Returns:
        [N, C] colours.
    """
    ensure_loaded()
    return torch.ops.cobgs.sh_colors(means.contiguous(), sh0.contiguous(), shN.contiguous(),
                                     center.to(means).contiguous(), int(degree))


def is_loaded() -> bool:
    """Whether the native ops are loaded in this process (never triggers a build)."""
    return _ready


def serves(device: torch.device) -> bool:
    """Whether the loaded native ops have kernels for ``device`` (CPU always; CUDA when
    the extension was built with its CUDA kernels). Never triggers a build: False until
    the extension is loaded."""
    if not _ready:
        return False
    if device.type == "cpu":
        return True
    if device.type == "cuda":
        global _cuda_kernels
        if _cuda_kernels is None:
            _cuda_kernels = build.has_cuda_kernels()
        return _cuda_kernels
    return False


_cuda_kernels: Optional[bool] = None


def check_serves(device: torch.device) -> None:
    """Load the extension and raise :class:`~cobgs.errors.InputError` naming why when it
    has no kernels for ``device``."""
    from cobgs.errors import InputError

    ensure_loaded()
    if serves(device):
        return
    if device.type == "cuda":
        plan = build.cuda_plan()
        raise InputError(f"the native backend has no CUDA kernels in this build "
                         f"({plan.get('reason', 'built without them')}); rebuild with "
                         f"`cobgs build --force` once that is fixed, or use "
                         f"backend=\"reference\" on {device}")
    raise InputError(f"the native backend runs on the CPU and on CUDA devices; got tensors on "
                     f"{device} (use backend=\"reference\")")


def ssim_mean_grad(x: Tensor, y: Tensor, g: Tensor) -> Tuple[Tensor, Tensor]:
    """Native ``cobgs::ssim_mean_grad`` (no autograd): mean SSIM of x [B, C, H, W] against
    a fixed y and d mean / dx, with the window g — :class:`cobgs.evaluate.ssim._MeanSSIM`'s
    forward and backward fused (the loss of every training iteration)."""
    ensure_loaded()
    dt = x.dtype
    return torch.ops.cobgs.ssim_mean_grad(x.contiguous(), y.to(dt).contiguous(), g.to(dt).contiguous())


def photometric_loss_grad(img: Tensor, ref: Tensor, g: Tensor,
                          ssim_weight: float) -> Tuple[Tensor, Tensor, Tensor]:
    """Native ``cobgs::photometric_loss_grad`` (no autograd): mean L1 and mean SSIM (window
    g) of img against a fixed ref, both channel-last [H, W, C] or [B, H, W, C], and the
    gradient of (1 - λ) L1 + λ (1 - SSIM) w.r.t. img, λ = ssim_weight."""
    ensure_loaded()
    dt = img.dtype
    return torch.ops.cobgs.photometric_loss_grad(img.contiguous(), ref.to(dt).contiguous(),
                                                 g.to(dt).contiguous(), float(ssim_weight))


def gauss_blur(x: Tensor, g: Tensor) -> Tensor:
    """Native ``cobgs::gauss_blur`` (no autograd): the separable zero-padded blur of
    :func:`cobgs.evaluate.ssim._blur`, vertical then horizontal, for x [B, K, H, W] and an
    odd-length kernel g [n]."""
    ensure_loaded()
    return torch.ops.cobgs.gauss_blur(x.contiguous(), g.to(x.dtype).contiguous())


def rasterize_native(means, quats, scales, opacities, features, viewmat, K, width, height,
                     background, pixel_labels, num_labels) -> RasterOutput:
    """:func:`cobgs.rasterize` on the native ops (inputs already validated)."""
    means2d, conics, depths, radii = project(means, quats, scales, viewmat, K, width, height)
    tile_offsets, flat_ids, prep = bin_tiles_tight(means2d, radii, depths, conics, opacities,
                                                   width, height)
    # The lists are bin_tiles_tight's own: no need to have the kernels' checks read back.
    image, trans, _n_contrib, counts, weights = blend(
        means2d, conics, opacities, features, background, tile_offsets, flat_ids, width,
        height, pixel_labels, num_labels, prep, check=False)
    has_labels = pixel_labels is not None
    return RasterOutput(image=image, alpha=1 - trans, transmittance=trans, radii=radii,
                        means2d=means2d, conics=conics, depths=depths,
                        label_counts=counts if has_labels else None,
                        label_weights=weights if has_labels else None)


@contextlib.contextmanager
def _path_switch(kind: str, on: bool):
    """Set the blending path switch ``kind`` ("cuda" / "cpu") for the block, then restore it."""
    ensure_loaded()
    setter = getattr(torch.ops.cobgs, f"set_{kind}_fast")
    before = setter(bool(on))
    try:
        yield
    finally:
        setter(before)


def cuda_fast_path(on: bool = True):
    """Within the block, the CUDA blending passes take the fast path (fused multiply-adds and
    the hardware exp; csrc/blend/blend_cuda.cuh) or, with ``on=False``, the exact one (every
    per-pixel decision made with the CPU kernels' roundings: bit-identical images and label
    counts); the previous setting is restored after. The fast path is the default
    (``COBGS_CUDA_EXACT=1`` selects the exact one at load); its stated tolerances against the
    exact path are tests/render/test_cuda.py's ``FAST_*``. A forward pass and its backward
    must run under the same setting (the backward recomputes the forward's decisions). The CPU
    kernels have a switch of their own, :func:`cpu_fast_path`."""
    return _path_switch("cuda", on)


def cuda_fast_path_on() -> bool:
    """Whether the CUDA blending passes take the fast path now."""
    ensure_loaded()
    return bool(torch.ops.cobgs.get_cuda_fast())


def cpu_fast_path(on: bool = True):
    """Within the block, the CPU blending kernels take the fast path (fused multiply-adds;
    csrc/common/cpu_isa.h) where the CPU has AVX2 and FMA, or with ``on=False`` the exact one
    (the default: bit-identical to the CUDA exact path and across instruction sets); the
    previous setting is restored after. ``COBGS_CPU_FAST=1`` turns it on at load;
    ``TrainConfig.fast_kernels`` turns it on for the training steps. Its stated tolerances
    against :mod:`cobgs.render.reference` and the exact path are
    tests/render/test_cpu_fast_path.py's. A forward pass and its backward must run under the
    same setting (the backward recomputes the forward's decisions)."""
    return _path_switch("cpu", on)


def cpu_fast_path_on() -> bool:
    """Whether the CPU blending kernels take the fast path now."""
    ensure_loaded()
    return bool(torch.ops.cobgs.get_cpu_fast())
