"""Render a :class:`~cobgs.gaussians.model.GaussianModel` at a :class:`~cobgs.render.camera.Camera`."""

from __future__ import annotations

from typing import Optional, Sequence

import torch
from torch import Tensor

from cobgs.render.camera import Camera
from cobgs.gaussians.model import GaussianModel


def render(
    model: GaussianModel,
    camera: Camera,
    background: Optional[Sequence[float] | Tensor] = None,
    *,
    features: Optional[Tensor] = None,
    sh_degree: Optional[int] = None,
    pixel_labels: Optional[Tensor] = None,
    num_labels: int = 2,
    backend: str = "native",
):
    """Rasterize the model's colours (or other ``features``) into ``camera``.

    Args:
        model: the Gaussians.
        camera: target camera (its ``width`` x ``height`` is the output size).
        background: [C] colour behind the Gaussians (default zeros).
        features: [N, C] per-Gaussian features to blend instead of the SH colour (e.g.
            mask labels); gradients flow into them.
        sh_degree: SH degree for the colour (default ``model.active_sh_degree``).
        pixel_labels: [H, W] int labels for per-Gaussian label statistics.
        num_labels: number of labels in ``pixel_labels``.
        backend: rasterizer backend ("native" or "reference").

    Returns:
        :class:`cobgs.render.rasterize.RasterOutput` (``image`` [H, W, C], ``alpha``, ``radii``
        [N], ``means2d`` [N, 2], ...).
    """
    from cobgs.render.rasterize import rasterize

    dev = model.device
    cam = camera.to(dev)
    if features is None:
        from cobgs.render import ops

        if backend == "native" and (dev.type == "cpu" or ops.serves(dev)):
            # One native op instead of ~60 small ATen ops (and their autograd nodes).

            deg = model.active_sh_degree if sh_degree is None else int(sh_degree)
            features = ops.sh_colors(model.data["means"], model.data["sh0"],
                                      model.data["shN"], cam.center, deg)
        else:
            features = model.colors(cam.center, degree=sh_degree)
    bg = None
    if background is not None:
        bg = torch.as_tensor(background, dtype=features.dtype, device=dev)
    return rasterize(
        model.means,
        model.quats,
        model.scales,
        model.opacities,
        features,
        cam.viewmat,
        cam.K,
        int(cam.width),
        int(cam.height),
        background=bg,
        pixel_labels=pixel_labels,
        num_labels=num_labels,
        backend=backend,
    )


def render_image(model: GaussianModel, camera: Camera, background=None, **kw) -> Tensor:
    """[H, W, 3] colour render without gradients (evaluation helper)."""
    with torch.no_grad():
        return render(model, camera, background, **kw).image
