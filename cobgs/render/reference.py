"""Pure-PyTorch reference of the native rasterizer ops (the test oracle).

Readable first, fast second: every public function here mirrors one native op in
``csrc/`` (``project``, ``bin_tiles``, ``blend``) and computes the same numbers with plain
tensor code, so its gradients come from autograd and can be compared with the
hand-written C++ backward. ``rasterize_reference`` composes them with the exact
signature of :func:`cobgs.rasterize`.

The rendering contract (docs/method.md §1, standard 3D Gaussian Splatting):

* **Camera.** ``viewmat`` [4, 4] maps world to camera, OpenCV axes (+x right, +y down,
  +z forward). ``K`` [3, 3] holds pixel intrinsics ``fx, fy, cx, cy`` (no skew). Pixel
  ``(i, j)`` (column, row) covers ``[i, i+1) x [j, j+1)`` and is sampled at its centre
  ``(i + 0.5, j + 0.5)`` (the COLMAP convention: ``cx = W/2`` is the image centre).
* **Projection (EWA).** Camera-space mean ``t = R m + T``; ``means2d = (fx tx/tz + cx,
  fy ty/tz + cy)`` in pixels; ``cov2d = J W Σ Wᵀ Jᵀ + 0.3 I`` (``LOWPASS_PX2``) where
  ``Σ = R_q S Sᵀ R_qᵀ`` and the Jacobian ``J`` is evaluated at ``tx/tz`` clamped to the
  field of view widened by 0.3 x tan(FoV/2) on each side (3DGS's 1.3 x tan(FoV/2) for a
  centred principal point; ``FRUSTUM_SLACK``). ``conic = cov2d⁻¹ = (a, b, c)``;
  ``radius = ceil(3 sqrt(λmax))`` with ``λmax = mid + sqrt(max(0.1, mid² - det))``.
* **Culling** (radius 0, zero outputs, zero gradients): ``tz <= NEAR_PLANE`` (0.01 scene
  units, gsplat's default; the original 3DGS code uses 0.2), a 2D covariance that is
  non-finite or has ``det <= 0``, a non-finite mean, a zero quaternion, or a 3-sigma box
  entirely off-screen (``mx + r <= 0`` or ``mx - r >= W``, likewise for y).
* **Tiles.** 16x16 pixels. A Gaussian is listed in every tile of
  ``[floor((mx - r)/16), ceil((mx + r)/16))`` x (same for y), clamped to the grid; each
  tile's list is sorted by camera depth ``tz`` (ties: lower Gaussian index first). A
  pixel considers exactly the Gaussians listed in its tile, front to back.
* **Blending** (per pixel, front to back; the rule of the 3DGS CUDA rasterizer)::

      d = pixel centre - mean2d
      power = -0.5 (a dx² + c dy²) - b dx dy;      skip if power > 0
      α = min(0.99, o · exp(power));               skip if α < 1/255
      if T · (1 - α) < 1e-4: stop, this Gaussian is NOT blended
      colour += f α T;   T = T · (1 - α)           (T starts at 1)

  ``image = colour + T_final · background``, ``alpha = 1 - T_final``. Each blended
  (Gaussian, pixel) pair is a *contribution*; the label statistics count exactly these.
  Gradients of ``min(0.99, ·)`` are zero where it clamps (``o·exp(power) > 0.99``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple

import torch
from torch import Tensor

from cobgs.gaussians.model import quat_to_rotmat

TILE_SIZE = 16
NEAR_PLANE = 0.01  # scene units; Gaussians with camera depth <= this are culled
LOWPASS_PX2 = 0.3  # EWA low-pass added to the 2D covariance diagonal (px²)
FRUSTUM_SLACK = 0.3  # Jacobian taken at tx/tz clamped to the FoV + 0.3 x tan(FoV/2)
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4


@dataclass
class RasterOutput:
    """What :func:`cobgs.rasterize` returns (H = height, W = width, N Gaussians).

    Attributes:
        image: Tensor  # [H, W, C] Σ f α T + T_final · background
        alpha: Tensor  # [H, W] accumulated opacity, 1 - transmittance
        transmittance: Tensor  # [H, W] T_final (>= 1e-4 wherever a Gaussian was blended)
        radii: Tensor  # [N] int32 3-sigma radius in pixels; 0 = culled
        means2d: Tensor  # [N, 2] projected means in pixels; differentiable (see rasterize)
        conics: Tensor  # [N, 3] inverse 2D covariance (a, b, c), px⁻²
        depths: Tensor  # [N] camera-space z of each Gaussian (0 if culled)
        label_counts: Optional[Tensor]  # [N, K] int32 contributed pixels per label
        label_weights: Optional[Tensor]  # [N, K] float32 Σ α·T per label
    """

    image: Tensor
    alpha: Tensor
    transmittance: Tensor
    radii: Tensor
    means2d: Tensor
    conics: Tensor
    depths: Tensor
    label_counts: Optional[Tensor] = None
    label_weights: Optional[Tensor] = None


def _projection_formulas(t, quats, scales, viewmat, K, width, height):
    """Every projection formula of the contract, without culling.

    ``t`` [N, 3] are camera-space means. Returns means2d [N, 2], cov2d entries
    (a, b, c) each [N], det [N], conics [N, 3] and the float radius [N].
    """
    R = viewmat[:3, :3]
    tx, ty, tz = t.unbind(-1)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]

    qn = quats / quats.norm(dim=-1, keepdim=True)
    M = quat_to_rotmat(qn, normalize=False) * scales[:, None, :]  # R_q · diag(s)
    cov_cam = R @ (M @ M.transpose(1, 2)) @ R.T  # W Σ Wᵀ

    # Jacobian of the pinhole projection at a clamped tx/tz (3DGS), keeping footprints of
    # Gaussians far outside the view from blowing up.
    lim_xp = (width - cx) / fx + FRUSTUM_SLACK * (0.5 * width / fx)
    lim_xn = cx / fx + FRUSTUM_SLACK * (0.5 * width / fx)
    lim_yp = (height - cy) / fy + FRUSTUM_SLACK * (0.5 * height / fy)
    lim_yn = cy / fy + FRUSTUM_SLACK * (0.5 * height / fy)
    txc = tz * torch.clamp(tx / tz, min=-lim_xn, max=lim_xp)
    tyc = tz * torch.clamp(ty / tz, min=-lim_yn, max=lim_yp)
    zero = torch.zeros_like(tz)
    J = torch.stack([
        fx / tz, zero, -fx * txc / (tz * tz),
        zero, fy / tz, -fy * tyc / (tz * tz),
    ], dim=-1).reshape(-1, 2, 3)
    cov2d = J @ cov_cam @ J.transpose(1, 2)
    a = cov2d[:, 0, 0] + LOWPASS_PX2
    b = cov2d[:, 0, 1]
    c = cov2d[:, 1, 1] + LOWPASS_PX2
    det = a * c - b * b
    conics = torch.stack([c / det, -b / det, a / det], dim=-1)

    means2d = torch.stack([fx * tx / tz + cx, fy * ty / tz + cy], dim=-1)
    mid = 0.5 * (a + c)
    lam = mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.1))
    radius = torch.ceil(3.0 * torch.sqrt(lam))
    return means2d, (a, b, c), det, conics, radius


def project_reference(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    scales: Tensor,  # [N, 3]
    viewmat: Tensor,  # [4, 4]
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
    near_plane: float = NEAR_PLANE,
) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """EWA projection and culling of 3D Gaussians (mirrors ``cobgs::project``).

    Args:
        means: Tensor  # [N, 3] world positions
        quats: Tensor  # [N, 4] rotations (w, x, y, z), need not be normalised
        scales: Tensor  # [N, 3] linear standard deviations along the local axes
        viewmat: Tensor  # [4, 4] world -> camera (OpenCV axes)
        K: Tensor  # [3, 3] pixel intrinsics (fx, fy, cx, cy; no skew)
        width, height: image size in pixels
        near_plane: Gaussians with camera depth <= this are culled

    Returns:
        means2d: Tensor  # [N, 2] projected means in pixels (0 if culled)
        conics: Tensor  # [N, 3] inverse 2D covariance (a, b, c) (0 if culled)
        depths: Tensor  # [N] camera-space z (0 if culled)
        radii: Tensor  # [N] int32 3-sigma radius in pixels, 0 = culled
    """
    t = means @ viewmat[:3, :3].T + viewmat[:3, 3]
    with torch.no_grad():
        m2, (a, b, c), det, conics, radius = _projection_formulas(
            t, quats, scales, viewmat, K, width, height)
        finite = (torch.isfinite(torch.stack([a, b, c, det], -1)).all(-1)
                  & torch.isfinite(m2).all(-1) & torch.isfinite(conics).all(-1))
        on_screen = ((m2[:, 0] + radius > 0) & (m2[:, 0] - radius < width)
                     & (m2[:, 1] + radius > 0) & (m2[:, 1] - radius < height))
        visible = ((t[:, 2] > near_plane) & (quats.norm(dim=-1) > 0) & finite
                   & (det > 0) & on_screen)

    # The differentiable pass runs on inputs where culled Gaussians are replaced by a
    # harmless one (on the optical axis, unit size): masking only the outputs would let
    # 0 · inf = NaN leak into the gradients of culled Gaussians.
    v = visible[:, None]
    t = torch.where(v, t, t.new_tensor([0.0, 0.0, 1.0]))
    quats = torch.where(v, quats, quats.new_tensor([1.0, 0.0, 0.0, 0.0]))
    scales = torch.where(v, scales, torch.ones_like(scales))
    m2, _, _, conics, radius = _projection_formulas(t, quats, scales, viewmat, K, width, height)

    zero = torch.zeros((), dtype=means.dtype, device=means.device)
    means2d = torch.where(v, m2, zero)
    conics = torch.where(v, conics, zero)
    depths = torch.where(visible, t[:, 2], zero)
    radii = torch.where(visible, radius.detach(), zero).to(torch.int32)
    return means2d, conics, depths, radii


def tile_grid(width: int, height: int) -> Tuple[int, int]:
    """Number of 16x16 tiles along x and y."""
    return (width + TILE_SIZE - 1) // TILE_SIZE, (height + TILE_SIZE - 1) // TILE_SIZE


def tile_rects(means2d: Tensor, radii: Tensor, width: int, height: int) -> Tensor:
    """Tile rectangle of every Gaussian, half-open, clamped to the grid.

    Args:
        means2d: Tensor  # [N, 2]
        radii: Tensor  # [N] int
    Returns:
        Tensor  # [N, 4] int64 (x0, y0, x1, y1); empty where radius is 0
    """
    tiles_x, tiles_y = tile_grid(width, height)
    r = radii.to(means2d.dtype)
    x0 = torch.floor((means2d[:, 0] - r) / TILE_SIZE).clamp(0, tiles_x)
    x1 = torch.ceil((means2d[:, 0] + r) / TILE_SIZE).clamp(0, tiles_x)
    y0 = torch.floor((means2d[:, 1] - r) / TILE_SIZE).clamp(0, tiles_y)
    y1 = torch.ceil((means2d[:, 1] + r) / TILE_SIZE).clamp(0, tiles_y)
    rect = torch.stack([x0, y0, x1, y1], dim=-1).to(torch.int64)
    rect[radii <= 0] = 0
    return rect


def bin_tiles_reference(
    means2d: Tensor,  # [N, 2]
    radii: Tensor,  # [N]
    depths: Tensor,  # [N]
    width: int,
    height: int,
) -> Tuple[Tensor, Tensor]:
    """Per-tile lists of Gaussians in depth order (mirrors ``cobgs::bin_tiles``).

    Returns:
        tile_offsets: Tensor  # [tiles_y * tiles_x + 1] int64; tile t (row-major) owns
                              # flat_ids[tile_offsets[t]:tile_offsets[t+1]]
        flat_ids: Tensor  # [M] int32 Gaussian indices, each tile's run sorted by depth
    """
    tiles_x, tiles_y = tile_grid(width, height)
    rect = tile_rects(means2d.detach(), radii, width, height)
    visible = torch.nonzero(radii > 0).flatten()
    # Stable sort: equal depths keep index order, which the native op reproduces.
    order = visible[torch.sort(depths.detach()[visible], stable=True).indices]
    x0, y0, x1, y1 = rect[order].unbind(-1)
    w = x1 - x0
    counts = w * (y1 - y0)
    gauss = torch.repeat_interleave(order, counts)
    first = torch.repeat_interleave(torch.cumsum(counts, 0) - counts, counts)
    local = torch.arange(gauss.numel(), device=gauss.device) - first
    wg = torch.repeat_interleave(w, counts)
    tile = (torch.repeat_interleave(y0, counts) + local // wg) * tiles_x + (
        torch.repeat_interleave(x0, counts) + local % wg)
    # Stable sort by tile keeps the depth order inside each tile.
    perm = torch.sort(tile, stable=True).indices
    flat_ids = gauss[perm].to(torch.int32)
    per_tile = torch.bincount(tile, minlength=tiles_x * tiles_y)
    tile_offsets = torch.zeros(tiles_x * tiles_y + 1, dtype=torch.int64, device=means2d.device)
    tile_offsets[1:] = torch.cumsum(per_tile, 0)
    return tile_offsets, flat_ids


def _blend_tile(m2, conics, opac, px, py):
    """Front-to-back blending of one tile's Gaussians (in depth order) at its pixels.

    m2 [n, 2], conics [n, 3], opac [n], px/py [P] pixel centres.
    Returns (weights α·T of contributions [n, P], contribution mask [n, P],
    final transmittance [P]).
    """
    dx = px[None, :] - m2[:, 0:1]
    dy = py[None, :] - m2[:, 1:2]
    a, b, c = conics[:, 0:1], conics[:, 1:2], conics[:, 2:3]
    power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
    alpha = torch.clamp(opac[:, None] * torch.exp(power), max=ALPHA_MAX)
    candidate = (power <= 0) & (alpha >= ALPHA_MIN)
    alpha = torch.where(candidate, alpha, torch.zeros_like(alpha))
    # T after each Gaussian if every candidate were blended; the first candidate that
    # would push T below T_MIN stops the pixel, so it and everything behind are dropped.
    t_after = torch.cumprod(1 - alpha, dim=0)
    stopper = candidate & (t_after < T_MIN)
    blended = candidate & (torch.cumsum(stopper.to(torch.int32), dim=0) == 0)
    alpha = torch.where(blended, alpha, torch.zeros_like(alpha))
    one_minus = 1 - alpha
    t_before = torch.cumprod(torch.cat([torch.ones_like(one_minus[:1]), one_minus[:-1]]), 0)
    weights = alpha * t_before
    t_final = torch.prod(one_minus, dim=0)
    return weights, blended, t_final


def blend_reference(
    means2d: Tensor,  # [N, 2]
    conics: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    features: Tensor,  # [N, C]
    background: Tensor,  # [C]
    tile_offsets: Tensor,  # [T + 1]
    flat_ids: Tensor,  # [M]
    width: int,
    height: int,
    pixel_labels: Optional[Tensor] = None,  # [H, W] int, -1 = ignore
    num_labels: int = 2,
) -> Tuple[Tensor, Tensor, Optional[Tensor], Optional[Tensor]]:
    """Tile-by-tile front-to-back blending (mirrors ``cobgs::blend``).

    Returns:
        image: Tensor  # [H, W, C]
        transmittance: Tensor  # [H, W] T_final
        label_counts: Tensor  # [N, K] int32, or None without pixel_labels
        label_weights: Tensor  # [N, K] float32 (not differentiable), or None
    """
    tiles_x, tiles_y = tile_grid(width, height)
    N, C = features.shape
    dev = features.device
    image = background.expand(height, width, C).clone()
    trans = features.new_ones(height, width)
    counts = weights_sum = None
    if pixel_labels is not None:
        counts = torch.zeros(N, num_labels, dtype=torch.int32, device=dev)
        weights_sum = torch.zeros(N, num_labels, dtype=torch.float32, device=dev)
    for ty in range(tiles_y):
        for tx in range(tiles_x):
            tile = ty * tiles_x + tx
            lo, hi = int(tile_offsets[tile]), int(tile_offsets[tile + 1])
            if lo == hi:
                continue
            ids = flat_ids[lo:hi].long()
            y0, x0 = ty * TILE_SIZE, tx * TILE_SIZE
            y1, x1 = min(y0 + TILE_SIZE, height), min(x0 + TILE_SIZE, width)
            ys, xs = torch.meshgrid(torch.arange(y0, y1, device=dev),
                                    torch.arange(x0, x1, device=dev), indexing="ij")
            px = xs.flatten().to(features.dtype) + 0.5
            py = ys.flatten().to(features.dtype) + 0.5
            w, blended, t_final = _blend_tile(
                means2d[ids], conics[ids], opacities[ids], px, py)
            colour = w.T @ features[ids] + t_final[:, None] * background
            image[y0:y1, x0:x1] = colour.reshape(y1 - y0, x1 - x0, C)
            trans[y0:y1, x0:x1] = t_final.reshape(y1 - y0, x1 - x0)
            if pixel_labels is not None:
                lab = pixel_labels[y0:y1, x0:x1].flatten().long()
                keep = lab >= 0
                onehot = torch.zeros(lab.numel(), num_labels, device=dev)
                onehot[keep, lab[keep]] = 1.0
                counts.index_add_(0, ids, (blended.to(torch.float32) @ onehot).round()
                                  .to(torch.int32))
                weights_sum.index_add_(0, ids, w.detach().to(torch.float32) @ onehot)
    return image, trans, counts, weights_sum


def rasterize_reference(
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
) -> RasterOutput:
    """The whole contract of :func:`cobgs.rasterize` in plain PyTorch (no validation).

    Inputs are assumed valid (``cobgs.rasterize(..., backend="reference")`` validates
    and then calls this); see :func:`cobgs.rasterize` for the argument documentation.
    """
    if background is None:
        background = features.new_zeros(features.shape[1])
    viewmat = viewmat.to(means.dtype)
    K = K.to(means.dtype)
    means2d, conics, depths, radii = project_reference(means, quats, scales, viewmat, K,
                                                       width, height)
    offsets, ids = bin_tiles_reference(means2d, radii, depths, width, height)
    image, trans, counts, weights = blend_reference(
        means2d, conics, opacities, features, background, offsets, ids, width, height,
        pixel_labels, num_labels)
    return RasterOutput(image=image, alpha=1 - trans, transmittance=trans, radii=radii,
                        means2d=means2d, conics=conics, depths=depths,
                        label_counts=counts, label_weights=weights)
