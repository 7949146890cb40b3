"""COB-GS mask labels: the rendered mask, the mask loss and the N⁺/N⁻ ambiguity scores.

docs/method.md §2 (paper Eqs. 2–7). Every Gaussian carries one raw label logit (the model extra
:data:`LABEL`); its label is ``m = sigmoid(logit)``, logit 0 (label 0.5) at the start.

* **Rendered mask** (Eq. 2): ``M(p) = Σ mᵢ αᵢ Tᵢ`` with the colour path's α / T cut-offs,
  no background term, not clamped. Geometry and opacity enter *detached*, so the mask
  loss reaches the labels only (docs/method.md §2 "mask loss reaches labels only").
* **Mask loss** (Eq. 3 as released): ``L = (−Σ G·M + λ Σ (1−G)·M) / (H·W)``, λ = 1; the
  per-pixel gradient dL/dM is −1/HW where G = 1 and +λ/HW where G = 0, so its sign is the
  supervising label. Pixels marked "don't care" (label −1) contribute nothing.
* **N⁺ / N⁻** (Eq. 5): per Gaussian, the number of contributing pixels whose dL/dM < 0
  (G = 1) and > 0 (G = 0). With the GT mask as ``pixel_labels`` the rasterizer's
  ``label_counts[:, 1]`` is N⁺ and ``label_counts[:, 0]`` is N⁻ — the same contributor
  rule as the blending (α ≥ 1/255, before the T < 1e-4 stop), computed in the forward
  pass, so no custom backward is needed.
* **Per-view score** (Eq. 6): ``r = |N⁺ − N⁻| / (N⁺ + N⁻ + 1e-6)``; a Gaussian with no
  contribution in the view scores 1.0 ("unseen counts as unambiguous", released code).
  The weighted variant (a config switch and an ablation row) uses Σ α·T per label
  instead of pixel counts; "unseen" is still "no contributing pixel".
* **Stage mean** (Eq. 7): scores summed over the iterations of one mask stage, divided by
  its length (2V); ambiguous where the mean < δ.
"""

from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor

from cobgs.render.camera import Camera
from cobgs.errors import InputError
from cobgs.gaussians.model import GaussianModel

from cobgs.configs import LABEL  # noqa: E402  (name of the per-Gaussian label-logit extra)
SCORE_EPS = 1e-6  # ε of Eq. 6, as in the released code


def ensure_label(model: GaussianModel, name: str = LABEL, reset: bool = True) -> Tensor:
    """Give ``model`` a label-logit extra ``name`` ([N] float32), all zeros when ``reset``.

    Fill value 0: Gaussians appended later (split children) start at label 0.5.
    """
    if name not in model.data:
        return model.add_extra(name, torch.zeros(len(model)), fill=0.0)
    t = model.data[name]
    if t.shape != (len(model),) or not t.is_floating_point():
        raise InputError(f"extra {name!r} must be a float [N] label logit, got {t.dtype} {list(t.shape)}")
    if reset:
        return model.set_tensor(name, torch.zeros_like(t))
    return t


def pixel_labels_from_mask(mask: Optional[Tensor], height: int, width: int, name: str = "mask") -> Tensor:
    """The GT mask of one view as rasterizer pixel labels.

    Args:
        mask: [H, W] bool (True = object), or integer with values in {−1, 0, 1}
            (−1 = don't care), or None (no annotation: every pixel is ignored).
        height, width: the view's size.
        name: for error messages (e.g. the view name).

    Returns:
        [H, W] int32 with 1 = object, 0 = not object, −1 = ignore.
    """
    if mask is None:
        return torch.full((height, width), -1, dtype=torch.int32)
    if not isinstance(mask, Tensor):
        raise InputError(f"{name}: mask must be a torch.Tensor, got {type(mask).__name__}")
    if tuple(mask.shape) != (height, width):
        raise InputError(f"{name}: mask must have shape [{height}, {width}] (the view size), "
                         f"got {list(mask.shape)}")
    if mask.dtype == torch.bool:
        return mask.to(torch.int32)
    if mask.dtype.is_floating_point or mask.dtype.is_complex:
        raise InputError(f"{name}: mask must be bool or integer (-1 = ignore, 0, 1), got {mask.dtype}; "
                         "binarise soft masks first")
    if mask.numel() and (int(mask.min()) < -1 or int(mask.max()) > 1):
        raise InputError(f"{name}: integer mask values must lie in {{-1, 0, 1}}, got "
                         f"{int(mask.min())}..{int(mask.max())}")
    return mask.to(torch.int32)


def render_label_mask(
    model: GaussianModel,
    camera: Camera,
    labels: Tensor,  # [N]
    pixel_labels: Optional[Tensor] = None,  # [H, W] int32
    backend: str = "native",
):
    """Render ``M = Σ labelᵢ αᵢ Tᵢ`` with geometry and opacity detached.

    Args:
        model: the Gaussians (only read).
        camera: target view.
        labels: [N] per-Gaussian value to blend (sigmoid of the logit for COB-GS, raw
            values for SA3D-GS); gradients flow into it and nowhere else.
        pixel_labels: [H, W] int32 GT labels for the N⁺/N⁻ statistics, or None.
        backend: rasterizer backend.

    Returns:
        :class:`cobgs.render.rasterize.RasterOutput`; ``image[..., 0]`` is M [H, W].
    """
    from cobgs.render.rasterize import rasterize

    cam = camera.to(model.device)
    return rasterize(
        model.means.detach(),
        model.quats.detach(),
        model.scales.detach(),
        model.opacities.detach(),
        labels[:, None],
        cam.viewmat,
        cam.K,
        int(cam.width),
        int(cam.height),
        background=None,  # docs/method.md §2: no background term in M
        pixel_labels=pixel_labels,
        num_labels=2,
        backend=backend,
    )


def mask_loss(rendered: Tensor, pixel_labels: Tensor, lam: float = 1.0, normalise: bool = True) -> Tensor:
    """COB-GS mask loss ``(−Σ G·M + λ Σ (1−G)·M) / (H·W)`` (docs/method.md §2).

    Args:
        rendered: [H, W] rendered mask M.
        pixel_labels: [H, W] int (1 = G, 0 = not G, −1 = ignored pixel).
        lam: λ, the weight of the background term (1 in COB-GS, 0.3 in SA3D-GS).
        normalise: divide by H·W (COB-GS) or not (SA3D-GS).

    Returns:
        scalar loss.
    """
    if rendered.shape != pixel_labels.shape:
        raise InputError(f"rendered mask {list(rendered.shape)} and labels {list(pixel_labels.shape)} differ")
    pos = (pixel_labels == 1).to(rendered.dtype)
    neg = (pixel_labels == 0).to(rendered.dtype)
    loss = -(pos * rendered).sum() + lam * (neg * rendered).sum()
    if normalise:
        loss = loss / rendered.numel()
    return loss


def view_scores(
    label_counts: Tensor,  # [N, 2] int32
    label_weights: Optional[Tensor] = None,  # [N, 2] float32
    use_weights: bool = False,
    lam: float = 1.0,
) -> Tensor:
    """Per-Gaussian ambiguity score of one view (Eq. 6, unseen = 1).

    Args:
        label_counts: [N, 2] pixels of label 0 (N⁻) and label 1 (N⁺) each Gaussian
            contributed to.
        label_weights: [N, 2] Σ α·T per label (needed when ``use_weights``).
        use_weights: score with Σ α·T instead of pixel counts (ablation).
        lam: λ of the mask loss; with λ = 0 the background pixels carry no gradient, so
            they count towards neither N⁺ nor N⁻ (the released code tests the sign).

    Returns:
        [N] float32 in [0, 1].
    """
    if label_counts.dim() != 2 or label_counts.shape[1] != 2:
        raise InputError(f"label_counts must be [N, 2], got {list(label_counts.shape)}")
    pos_n = label_counts[:, 1].to(torch.float32)
    neg_n = label_counts[:, 0].to(torch.float32)
    if lam == 0:
        neg_n = torch.zeros_like(neg_n)
    if use_weights:
        if label_weights is None or label_weights.shape != label_counts.shape:
            raise InputError("use_weights needs label_weights of the same shape as label_counts")
        pos, neg = label_weights[:, 1].to(torch.float32), label_weights[:, 0].to(torch.float32)
        if lam == 0:
            neg = torch.zeros_like(neg)
    else:
        pos, neg = pos_n, neg_n
    r = (pos - neg).abs() / (pos + neg + SCORE_EPS)
    unseen = (pos_n + neg_n) == 0
    return torch.where(unseen, torch.ones_like(r), r)


def object_share(label_weights: Tensor) -> Tensor:
    """Per-Gaussian ambiguity as the *object* sees it, in one view (``RefineConfig.split_object_share``).

    Eq. 6 judges a Gaussian against its own footprint: one that covers a small object and a
    large stretch of background scores near 1 (unambiguous) however much of the object it
    carries. What it costs the object's mask is its minority part, whichever label it takes:
    ``min(Σ α·T over object pixels, Σ α·T over background pixels)``. This returns that as a
    share of the object's whole Σ α·T in the view (all Gaussians), 0 where the view shows no
    object.

    Args:
        label_weights: [N, 2] Σ α·T per label (0 background, 1 object) of one view.

    Returns:
        [N] float32 ≥ 0.
    """
    if label_weights.dim() != 2 or label_weights.shape[1] != 2:
        raise InputError(f"label_weights must be [N, 2], got {list(label_weights.shape)}")
    w = label_weights.to(torch.float64)
    total = w[:, 1].sum()
    if total <= 0:
        return torch.zeros(len(w), dtype=torch.float32, device=w.device)
    return (torch.minimum(w[:, 0], w[:, 1]) / total).to(torch.float32)


class ScoreAccumulator:
    """Sum of per-view scores over one mask stage (Eq. 7).

    Args:
        n: number of Gaussians (the accumulator must be reset after any structural edit).
    """

    def __init__(self, n: int, device: torch.device | str = "cpu"):
        self.device = torch.device(device)
        self.reset(n)

    def reset(self, n: int) -> None:
        self.sum = torch.zeros(n, dtype=torch.float64, device=self.device)
        self.iterations = 0

    def add(self, scores: Tensor) -> None:
        """Add one view's [N] scores."""
        if scores.shape != self.sum.shape:
            raise InputError(f"scores must be [{self.sum.shape[0]}] (Gaussians at the last reset), "
                             f"got {list(scores.shape)}")
        self.sum += scores.detach().to(self.sum.device, torch.float64)
        self.iterations += 1

    def mean(self, length: Optional[int] = None) -> Tensor:
        """[N] float32 stage mean: the sum divided by ``length`` (the stage length, 2V;
        default the number of iterations added, equal to it in a full stage)."""
        d = self.iterations if length is None else int(length)
        if d <= 0:
            raise InputError("no scores accumulated yet")
        return (self.sum / d).to(torch.float32)

    def ambiguous(self, delta: float, length: Optional[int] = None) -> Tensor:
        """[N] bool: stage mean < δ."""
        return self.mean(length) < delta
