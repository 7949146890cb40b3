"""COB-GS structural edits: boundary-adaptive splitting (BAGS) and the RAEM pruning.

docs/method.md §2:

* **Boundary-adaptive split.** Of the ambiguous Gaussians (stage-mean score < δ), those
  whose largest scale exceeds ``0.01 × scene extent`` are each replaced by 2 children:
  position ``μ + R·N(0, diag(s))`` (a sample of the parent), scale ``s / 1.6``, the same
  rotation, SH and opacity, label logit reset to 0; the parent is removed. Every
  optimizer passed in has its Adam moments edited the same way (children start at 0).
* **RAEM** (robustness against erroneous masks), at the end of the refinement:
  ``"released"`` removes every ambiguous Gaussian (the released code, no size test);
  ``"paper"`` removes only the *tiny* ambiguous ones (the paper's description, "scales
  smaller than the pixel scale"). Our precise definition of tiny: the Gaussian's
  *pixel footprint* — its largest standard deviation projected at its depth,
  ``max(s) · max(fx, fy) / z`` pixels — is below ``footprint_px`` (1 px) in **every**
  training view that sees it, i.e. its maximum over those views is < 1 px. A view sees
  a Gaussian when its centre is in front of the near plane (z > 0.01) and projects
  inside the image. (The maximum, not the mean: a Gaussian that covers several pixels in
  some view is visible structure there and removing it would leave a hole.)
"""

from __future__ import annotations

from typing import Iterable, Optional, Sequence

import torch
from torch import Tensor

from cobgs.render.camera import Camera
from cobgs.errors import InputError
from cobgs.gaussians.model import GaussianModel
from cobgs.render.reference import NEAR_PLANE

from cobgs.configs import RAEM_VARIANTS  # noqa: E402,F401


def split_candidates(model: GaussianModel, ambiguous: Tensor, extent: float, size_fraction: float = 0.01) -> Tensor:
    """[N] bool: ambiguous Gaussians with max scale > ``size_fraction × extent``."""
    if ambiguous.dtype != torch.bool or ambiguous.shape != (len(model),):
        raise InputError(f"ambiguous must be a bool [{len(model)}] tensor, got {ambiguous.dtype} "
                         f"{list(ambiguous.shape)}")
    big = model.scales.detach().max(dim=1).values > size_fraction * extent
    return ambiguous & big


def boundary_split(
    model: GaussianModel,
    ambiguous: Tensor,  # [N] bool
    extent: float,
    *,
    size_fraction: float = 0.01,
    n_children: int = 2,
    scale_divisor: float = 1.6,
    reset: Sequence[str] = (),
    optimizers: Iterable = (),
    generator: Optional[torch.Generator] = None,
) -> int:
    """Split the large ambiguous Gaussians in place (see the module docstring).

    Args:
        model: edited in place; children are appended after the kept Gaussians.
        ambiguous: [N] bool, stage-mean score < δ.
        extent: scene extent (world units).
        size_fraction: split only where max scale > this × extent (0.01).
        n_children: children per parent (2).
        scale_divisor: child scale = parent scale / this (1.6).
        reset: extras the children do not inherit (set to their fill value): the label
            logit of the object being refined.
        optimizers: every optimizer owning the model's tensors (label and texture).
        generator: RNG of the position samples.

    Returns:
        the number of parents split.
    """
    sel = split_candidates(model, ambiguous, extent, size_fraction)
    n = int(sel.sum())
    if n == 0:
        return 0
    children = model.split_children(sel, n_children, scale_divisor, reset=tuple(reset), generator=generator)
    model.replace(sel, children, list(optimizers))
    return n


def pixel_footprint(model: GaussianModel, cameras: Sequence[Camera], chunk: int = 1 << 20) -> Tensor:
    """Largest pixel footprint of each Gaussian over the views that see it.

    Footprint in one view = ``max(s) · max(fx, fy) / z`` (its largest standard deviation
    in pixels at its depth); a view sees the Gaussian when ``z > NEAR_PLANE`` and its
    centre projects inside the image.

    Args:
        model: the Gaussians.
        cameras: the training views.
        chunk: Gaussians per batch (memory bound).

    Returns:
        [N] float32; 0 for Gaussians no view sees.
    """
    means = model.means.detach()
    smax = model.scales.detach().max(dim=1).values
    out = torch.zeros(len(model), dtype=torch.float32, device=means.device)
    for cam in cameras:
        R = cam.viewmat[:3, :3].to(means)
        t = cam.viewmat[:3, 3].to(means)
        f = max(cam.fx, cam.fy)
        for lo in range(0, len(model), chunk):
            pc = means[lo : lo + chunk] @ R.T + t
            z = pc[:, 2]
            zs = z.clamp_min(1e-12)
            u = pc[:, 0] / zs * cam.fx + cam.cx
            v = pc[:, 1] / zs * cam.fy + cam.cy
            seen = (z > NEAR_PLANE) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
            fp = torch.where(seen, smax[lo : lo + chunk] * f / zs, torch.zeros_like(zs))
            out[lo : lo + chunk] = torch.maximum(out[lo : lo + chunk], fp.to(torch.float32))
    return out


def raem_prune_mask(
    model: GaussianModel,
    ambiguous: Tensor,  # [N] bool
    variant: str,
    cameras: Sequence[Camera] = (),
    footprint_px: float = 1.0,
    spare: Optional[Tensor] = None,
) -> Tensor:
    """[N] bool: the Gaussians RAEM removes (see the module docstring).

    Args:
        model: the refined Gaussians.
        ambiguous: [N] bool, final stage-mean score < δ.
        variant: "off", "released" (every ambiguous one) or "paper" (ambiguous and
            footprint < ``footprint_px`` in every training view that sees it).
        cameras: training views (for "paper").
        footprint_px: the pixel-footprint threshold of "paper".
        spare: [N] bool, Gaussians never removed whatever the variant says (None: none;
            ``RefineConfig.raem_spare_object`` passes the labels' foreground).
    """
    if variant not in RAEM_VARIANTS:
        raise InputError(f"raem must be one of {RAEM_VARIANTS}, got {variant!r}")
    if ambiguous.dtype != torch.bool or ambiguous.shape != (len(model),):
        raise InputError(f"ambiguous must be a bool [{len(model)}] tensor")
    if variant == "off":
        return torch.zeros_like(ambiguous)
    if spare is not None:
        ambiguous = ambiguous & ~spare.to(ambiguous.device)
    if variant == "released":
        return ambiguous.clone()
    if not cameras:
        raise InputError('raem="paper" needs the training cameras to measure pixel footprints')
    return ambiguous & (pixel_footprint(model, cameras) < footprint_px)
