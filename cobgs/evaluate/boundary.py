"""What COB-GS's boundaries depend on, measured on a trained scene before any refinement.

COB-GS splits the Gaussians that straddle an object's mask boundary (BAGS) and the
segmentation can only be as sharp as the scene's detail there. Two measures, per object:

* :func:`straddling_gaussians`: the Gaussians whose 3-sigma footprint crosses the object's mask
  boundary in at least one training view (the projected mean is nearer the boundary than the
  footprint's radius), with their count, sizes and opacities;
* :func:`band_psnr`: the PSNR of a render in a band of a few pixels around the mask's edge
  (:func:`edge_band`), beside the whole image's: a recipe can raise the whole-image PSNR and
  lose detail exactly where the boundaries are.
"""

from __future__ import annotations

import math
from typing import Optional, Sequence

import numpy as np


def edge_band(mask: np.ndarray, width: int = 3) -> np.ndarray:
    """The pixels within ``width`` pixels of ``mask``'s edge (inside or outside): the mask
    dilated XOR eroded with a (2 width + 1)-pixel square. Empty for an empty or full mask."""
    import cv2

    m = np.asarray(mask).astype(bool).astype(np.uint8)
    if width <= 0 or not m.any() or m.all():
        return np.zeros(m.shape, bool)
    k = np.ones((2 * width + 1, 2 * width + 1), np.uint8)
    return cv2.dilate(m, k).astype(bool) ^ cv2.erode(m, k, borderType=cv2.BORDER_REPLICATE).astype(bool)


def band_psnr(render: np.ndarray, reference: np.ndarray, band: Optional[np.ndarray] = None) -> float:
    """PSNR (dB) of ``render`` against ``reference`` (uint8 or [0, 1] floats, [H, W, C]) over the
    pixels of ``band`` (all pixels when None); nan for an empty band, inf for equal pixels."""
    a, b = _unit(render), _unit(reference)
    if a.shape != b.shape:
        raise ValueError(f"render {a.shape} and reference {b.shape} differ in size")
    sel = np.ones(a.shape[:2], bool) if band is None else np.asarray(band, bool)
    if not sel.any():
        return float("nan")
    mse = float(np.mean((a[sel] - b[sel]) ** 2))
    return float("inf") if mse == 0 else 10.0 * math.log10(1.0 / mse)


def _unit(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x)
    return x.astype(np.float64) / 255.0 if x.dtype == np.uint8 else x.astype(np.float64)


def _boundary_distance(mask: np.ndarray) -> np.ndarray:
    """Per pixel, the distance (px) to the nearest pixel on the other side of the mask's edge."""
    import cv2

    m = np.asarray(mask).astype(bool)
    inside = cv2.distanceTransform(m.astype(np.uint8), cv2.DIST_L2, 3)  # to the nearest outside pixel
    outside = cv2.distanceTransform((~m).astype(np.uint8), cv2.DIST_L2, 3)  # to the nearest inside pixel
    return np.where(m, inside, outside)


def straddling_gaussians(model, cameras: Sequence, masks: Sequence[Optional[np.ndarray]]) -> dict:
    """The Gaussians of ``model`` whose 3-sigma footprint crosses the mask boundary in at least
    one view (module docstring).

    Args:
        model: a :class:`cobgs.gaussians.GaussianModel`.
        cameras: :class:`cobgs.render.camera.Camera` per view.
        masks: the object's bool mask per view at the camera's size (None: no mask there; an empty
            or full mask has no boundary).

    Returns:
        ``{"gaussians": N, "straddling": n, "mask": bool [N] (numpy), "radius_px_median",
        "scale_median", "opacity_median", "views": views with a boundary}``: the medians are over
        the straddling Gaussians (their footprint radius in the views they straddle, their largest
        world-space scale, their opacity).
    """
    import torch

    from cobgs.render.reference import project_reference

    means = model.means.detach()
    quats = model.quats.detach()
    scales = model.scales.detach()
    n = means.shape[0]
    hit = np.zeros(n, bool)
    radius_sum = np.zeros(n)
    radius_n = np.zeros(n)
    views = 0
    for cam, mask in zip(cameras, masks):
        if mask is None:
            continue
        m = np.asarray(mask).astype(bool)
        if not m.any() or m.all():
            continue
        views += 1
        dist = _boundary_distance(m)
        with torch.no_grad():
            m2, _, _, radii = project_reference(means, quats, scales, cam.viewmat.to(means), cam.K.to(means),
                                                int(cam.width), int(cam.height))
        xy = m2.cpu().numpy()
        r = radii.cpu().numpy().astype(np.float64)
        h, w = m.shape
        px = np.clip(np.round(xy[:, 0] - 0.5).astype(np.int64), 0, w - 1)
        py = np.clip(np.round(xy[:, 1] - 0.5).astype(np.int64), 0, h - 1)
        on = (r > 0) & (xy[:, 0] >= 0) & (xy[:, 0] < w) & (xy[:, 1] >= 0) & (xy[:, 1] < h)
        crosses = on & (dist[py, px] < r)
        hit |= crosses
        radius_sum[crosses] += r[crosses]
        radius_n[crosses] += 1
    sel = hit
    opac = model.opacities.detach().cpu().numpy().reshape(-1)
    scale = scales.max(dim=1).values.cpu().numpy()

    def med(x):
        return float(np.median(x)) if x.size else float("nan")

    return {"gaussians": int(n), "straddling": int(sel.sum()), "mask": sel,
            "radius_px_median": med(radius_sum[sel] / np.maximum(radius_n[sel], 1)),
            "scale_median": med(scale[sel]), "opacity_median": med(opac[sel]), "views": views}


__all__ = ["band_psnr", "edge_band", "straddling_gaussians"]
