"""gsplat's ``rasterization`` as the training steps' forward pass (``TrainConfig.rasterizer =
"gsplat"``, issue 60): the same trainer, data, schedule and densification, only the rasterizer
differs, so "ours against gsplat" is measured on a whole training. CUDA only (gsplat has no CPU
kernels); evaluation, refinement and label counts stay ours.

The model's SH coefficients go to gsplat as they are (its colour is 3DGS's: SH evaluated at
the view direction, + 0.5, clamped at 0), the background too; the densification statistics
read the gradient of gsplat's projected means (pixels, as ours) and its radii (the larger of
the two axes where gsplat gives two). Unverified without a GPU: ``make gpu-check`` trains fern
with both rasterizers (tests/benchmarks/gpu_check.sh).
"""

from __future__ import annotations

from dataclasses import dataclass

from cobgs.errors import InputError


def check_gsplat(device) -> None:
    """Refuse, in one line, a training that asks for gsplat where it cannot run.

    Raises:
        InputError: gsplat not importable, or a device other than CUDA.
    """
    try:
        import gsplat  # noqa: F401
    except Exception as exc:  # noqa: BLE001 - an import that fails for any reason: not usable
        raise InputError(f"TrainConfig.rasterizer = 'gsplat' needs gsplat ({type(exc).__name__}: {exc}); "
                         "pip install gsplat on a machine with CUDA, or train with rasterizer = 'ours'") from None
    if getattr(device, "type", str(device)) != "cuda":
        raise InputError(f"TrainConfig.rasterizer = 'gsplat' runs on CUDA only (gsplat has no CPU kernels), but the "
                         f"scene is on {device}: set device = 'cuda', or train with rasterizer = 'ours'")


@dataclass
class GsplatOutput:
    """What the trainer reads of a forward pass (as :class:`cobgs.render.rasterize.RasterOutput`)."""

    image: object  # [H, W, 3]
    alpha: object  # [H, W]
    means2d: object  # [N, 2] pixels, with its gradient after the backward
    radii: object  # [N] int pixels, 0 = culled


def render_gsplat(model, camera, background) -> GsplatOutput:
    """The model rendered by gsplat's ``rasterization`` at ``camera`` over ``background``."""
    import torch
    from gsplat import rasterization

    dev = model.device
    cam = camera.to(dev)
    colors = torch.cat([model.data["sh0"], model.data["shN"]], dim=1)  # [N, K, 3] SH coefficients
    bg = torch.as_tensor(background, dtype=colors.dtype, device=dev).reshape(1, 3)
    rgb, alpha, meta = rasterization(
        model.means, model.quats, model.scales, model.opacities, colors,
        cam.viewmat[None].to(colors.dtype), cam.K[None].to(colors.dtype), int(cam.width), int(cam.height),
        sh_degree=int(model.active_sh_degree), backgrounds=bg, packed=False)
    means2d = meta["means2d"]
    radii = meta["radii"]
    if radii.dim() == 3:  # gsplat >= 1.5: per-axis radii [C, N, 2]
        radii = radii.max(dim=-1).values
    return GsplatOutput(image=rgb[0], alpha=alpha[0, ..., 0], means2d=_PerCamera(means2d), radii=radii[0])


class _PerCamera:
    """gsplat's projected means of the one camera: ``retain_grad`` / ``grad`` as the trainer uses
    them, on the batched tensor gsplat's backward writes."""

    def __init__(self, batched):
        self._t = batched

    def retain_grad(self) -> None:
        self._t.retain_grad()

    @property
    def grad(self):
        return None if self._t.grad is None else self._t.grad[0]


__all__ = ["GsplatOutput", "check_gsplat", "render_gsplat"]
