"""Per-Gaussian label votes, and the object-render check of the foreground.

* :func:`label_votes` — one forward pass per view accumulates, per Gaussian and ground-truth
  label, Σ α·T over the pixels of that label (FlashSplat's statistic, and the closed form the
  mask stages' label optimisation converges to: object where the object votes exceed λ × the
  background votes).
* :func:`object_render_check` — this project's addition to COB-GS (``RefineConfig.object_check
  = "visible"``; docs/benchmarks/refinement_trajectory.md has the measurements behind it).
  The mask loss judges each Gaussian by what it contributes to the *scene* render, where
  other surfaces may hide most of it; the segmented object is used — and evaluated — rendered
  *alone*, where nothing hides it. A Gaussian seen only weakly (mostly hidden behind others in
  the training views) can thus become foreground on little evidence and then spill beyond the
  object's outline in the object's own render. The check renders the foreground alone in every
  training view and votes again, per Gaussian, with the same rule as the mask loss (object
  where Σ α·T over object pixels > λ × that over background pixels), on that render; pixels
  where the object is hidden in the scene render by something else are left out (a modal mask
  says nothing about them: there the object's render may rightly show what is occluded). A
  Gaussian that the check outvotes leaves the foreground; it stays in the scene (and in neither
  set, like an undecided label); one the check cannot see at all (every pixel of it left out)
  keeps its label's verdict.
* The check's keep rule (``RefineConfig.object_check_rule``). ``"votes"``: the mask loss's rule
  above, per Gaussian. ``"iou"`` (issue 59 item 2): a Gaussian leaves the foreground only when
  the object's render agrees better with the masks without it, by the intersection over union
  the object is scored with. With a Gaussian's object and background votes a and b, the
  foreground's summed votes A and B and the masks' object pixels M (all over the checked
  pixels), the soft IoU A / (M + B) rises when the Gaussian goes exactly when a / b < A / (M + B).
  Removing such Gaussians raises the IoU, so the rule is applied until nothing changes (a few
  rounds). It never removes a Gaussian the votes rule keeps (the bar is min(λ, IoU) ≤ λ). On an
  object the foreground covers well (IoU near 1) it is the votes rule; on a thin or tiny object
  whose only Gaussians straddle its outline (a pole drawn by one Gaussian with 40 % of its
  weight on the pole), removing them leaves nothing, and the rule keeps them.
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor

from cobgs.data.scene import View
from cobgs.render.image import render
from cobgs.errors import InputError
from cobgs.gaussians.model import GaussianModel


def label_votes(model: GaussianModel, views: Sequence[View], pixel_labels: Sequence[Tensor], num_labels: int,
                backend: str = "native") -> Tensor:
    """[N, num_labels] Σ α·T per ground-truth label over all views (one forward pass per
    view; pixel labels −1 are ignored)."""
    m = model
    acc = torch.zeros(len(m), num_labels, dtype=torch.float64, device=m.device)
    feats = torch.zeros(len(m), 1, device=m.device)
    with torch.no_grad():
        for v, lab in zip(views, pixel_labels):
            out = render(m, v.camera, features=feats, pixel_labels=lab.to(m.device), num_labels=num_labels,
                         backend=backend)
            acc += out.label_weights.to(torch.float64)
    return acc


def _mask_render(model: GaussianModel, values: Tensor, view: View, backend: str) -> Tensor:
    with torch.no_grad():
        out = render(model, view.camera, features=values[:, None].to(model.means.dtype).contiguous(),
                     backend=backend)
    return out.image[..., 0]


def _judged_pixels(model: GaussianModel, obj: GaussianModel, values: Tensor, view: View, labels: Tensor,
                   backend: str) -> tuple[Tensor, Tensor]:
    """``(alone, judged)``: the object ``obj`` rendered alone and drawn above 0.5, and ``labels``
    with the background pixels where the object is hidden in the scene (``model`` rendered with
    the object's ``values``: the object as the scene shows it) set to −1: there something else
    hides it, and a modal mask says nothing about what lies behind."""
    if len(obj):
        alone = _mask_render(obj, torch.ones(len(obj), device=model.device), view, backend) > 0.5
    else:
        alone = torch.zeros(labels.shape, dtype=torch.bool, device=labels.device)
    visible = _mask_render(model, values, view, backend) > 0.5
    judged = labels.clone()
    judged[(judged == 0) & alone & ~visible] = -1
    return alone, judged


def edge_band(labels: Tensor, radius: int) -> Tensor:
    """[H, W] bool: the pixels within ``radius`` pixels (a square neighbourhood) of an edge
    between object (1) and background (0) pixels of ``labels`` (ignored pixels, −1, are neither)."""
    if radius <= 0:
        return torch.zeros(labels.shape, dtype=torch.bool, device=labels.device)
    k = 2 * radius + 1
    pool = torch.nn.functional.max_pool2d

    def grow(m: Tensor) -> Tensor:
        return pool(m[None, None].float(), k, stride=1, padding=radius)[0, 0] > 0

    obj, bg = labels == 1, labels == 0
    return (grow(obj) & grow(bg)) & (obj | bg)


def object_render_check(model: GaussianModel, foreground: Tensor, views: Sequence[View],
                        pixel_labels: Sequence[Tensor], mask_lambda: float = 1.0,
                        backend: str = "native", edge_px: int = 0, rule: str = "votes") -> Tensor:
    """The foreground after the object-render check (module docstring).

    Args:
        model: the refined scene.
        foreground: [N] bool, the foreground to check.
        views: the training views; pixel_labels: their masks as pixel labels (1 object,
            0 background, −1 ignored; :func:`cobgs.refine.scores.pixel_labels_from_mask`).
        mask_lambda: λ of the mask loss (the weight of background votes).
        edge_px: pixels within this distance of a mask edge are left out of the votes
            (``RefineConfig.object_check_edge_px``; 0: none).
        rule: "votes", "iou" or "removal" (module docstring; ``RefineConfig.object_check_rule``).

    Returns:
        [N] bool: ``foreground`` without the Gaussians the check outvotes.
    """
    idx = torch.nonzero(foreground).squeeze(1)
    if len(idx) == 0:
        return foreground.clone()
    obj = model.select(idx)
    fg_values = foreground.to(model.means.dtype)
    checked = []
    for v, lab in zip(views, pixel_labels):
        lab = lab.to(model.device)
        _, q = _judged_pixels(model, obj, fg_values, v, lab, backend)
        if edge_px > 0:  # near the mask's edge: the mask is least reliable there
            q[edge_band(lab, edge_px)] = -1
        checked.append(q)
    w = label_votes(obj, views, checked, 2, backend)
    out = foreground.clone()
    # a Gaussian the check cannot see (every pixel of it left out) keeps its label's verdict
    unseen = w.sum(dim=1) == 0
    if rule == "votes":
        out[idx] = object_by_votes(w, mask_lambda) | unseen
    elif rule == "iou":
        object_pixels = float(sum(int((q == 1).sum()) for q in checked))
        out[idx] = iou_keep(w[:, 1], w[:, 0], object_pixels, mask_lambda) | unseen
    elif rule == "removal":
        out[idx] = removal_keep(obj, views, checked, object_by_votes(w, mask_lambda) | unseen, backend)
    else:
        raise InputError(f"object check rule must be 'votes', 'iou' or 'removal', got {rule!r}")
    return out


def removal_gains(model: GaussianModel, views: Sequence[View], pixel_labels: Sequence[Tensor],
                  backend: str = "native") -> tuple[Tensor, float, float]:
    """What removing each Gaussian alone takes from the model's coverage (its rendered alpha).

    The coverage of a pixel, O = 1 − Π (1 − α_j), is linear in each α_i, so removing Gaussian i
    lowers it by exactly α_i · Π_{j≠i} (1 − α_j) = o_i · ∂O/∂o_i (o_i its opacity): the
    gradient of the coverage with respect to the opacities gives every single removal's effect
    at once, in one forward and one backward pass per view and label. Unlike the Σ α·T votes
    (:func:`label_votes`), it counts a pixel a Gaussian draws only as far as the Gaussians
    behind it would not draw it anyway.

    Returns:
        gains: [N, 2] float64, per Gaussian the coverage removed on the background (column 0)
            and object (column 1) pixels of ``pixel_labels`` over all views;
        covered_object, covered_background: Σ O over those object / background pixels.
    """
    m = model.clone()
    logits = m.data["opacity_logits"]
    logits.requires_grad_(True)
    ones = torch.ones(len(m), 1, device=m.device)
    gains = torch.zeros(len(m), 2, dtype=torch.float64, device=m.device)
    covered = [0.0, 0.0]
    for v, lab in zip(views, pixel_labels):
        lab = lab.to(m.device)
        cov = render(m, v.camera, features=ones, backend=backend).image[..., 0]
        for k in (0, 1):
            sel = (lab == k).to(cov.dtype)
            total = (cov * sel).sum()
            covered[k] += float(total.detach())
            (g,) = torch.autograd.grad(total, logits, retain_graph=(k == 0))
            gains[:, k] += g.to(torch.float64)
    o = torch.sigmoid(logits.detach()).to(torch.float64)
    # ∂O/∂l = ∂O/∂o · o (1 − o), so o · ∂O/∂o = ∂O/∂l / (1 − o)
    gains /= (1.0 - o).clamp_min(1e-12)[:, None]
    return gains, covered[1], covered[0]


def removal_keep(model: GaussianModel, views: Sequence[View], pixel_labels: Sequence[Tensor],
                 always: Tensor, backend: str = "native", max_rounds: int = 20) -> Tensor:
    """[n] bool: the Gaussians of ``model`` (the foreground, rendered alone) the ``"removal"``
    rule keeps: those in ``always`` (the votes rule's verdict), and every other one whose removal
    alone would not raise the object's soft IoU with the masks, Σ_obj O / (M + Σ_bg O) (O the
    coverage, M the object pixels; :func:`removal_gains`). Those whose removal raises it go
    together, and the rule is applied again to what is left until nothing changes."""
    object_pixels = float(sum(int((q == 1).sum()) for q in pixel_labels))
    keep = torch.ones(len(model), dtype=torch.bool, device=model.device)
    for _ in range(max_rounds):
        idx = torch.nonzero(keep).squeeze(1)
        gains, inter, bg = removal_gains(model.select(idx), views, pixel_labels, backend)
        iou = inter / max(object_pixels + bg, 1e-300)
        # removing one alone raises the IoU exactly when a / b < IoU (a, b its gains)
        goes = (gains[:, 1] < iou * gains[:, 0]) & ~always[idx]
        if not bool(goes.any()):
            break
        keep[idx[goes]] = False
    return keep


def object_by_votes(votes: Tensor, mask_lambda: float = 1.0) -> Tensor:
    """[N] bool: the Gaussians whose votes say object, object Σ α·T > λ × background Σ α·T
    (``votes``: :func:`label_votes` with labels 0 = background, 1 = object). This is the mask
    loss's closed form, as FlashSplat's assignment reads it."""
    return votes[:, 1] > mask_lambda * votes[:, 0]


def undecided_by_votes(values: Tensor, votes: Tensor, mask_lambda: float = 1.0, low: float = 0.1,
                       high: float = 0.9) -> Tensor:
    """[N] bool: the Gaussians the refinement left undecided (``low < value < high``) whose
    votes (:func:`label_votes` of the training masks in the scene render, every Gaussian
    occluding as in the scene) say object (:func:`object_by_votes`).

    ``RefineConfig.in_scene_undecided = "votes"`` adds them to the object within the scene.
    """
    return (values > low) & (values < high) & object_by_votes(votes, mask_lambda)


def iou_keep(a: Tensor, b: Tensor, object_pixels: float, mask_lambda: float = 1.0,
             max_rounds: int = 100) -> Tensor:
    """[n] bool: the Gaussians the ``"iou"`` rule keeps (module docstring).

    Args:
        a, b: [n] each Gaussian's votes on the object's and the background's pixels.
        object_pixels: the masks' object pixels M over the checked views.
        mask_lambda: λ; the bar is min(λ, soft IoU), so nothing the votes rule keeps goes.

    A Gaussian stays when ``a >= bar · b`` (strictly below the bar it goes); the soft IoU
    Σa / (M + Σb) of the kept ones sets the next round's bar, until the set stops changing (it
    only shrinks, and the IoU only rises, so this ends; ``max_rounds`` bounds it all the same).
    """
    a, b = a.to(torch.float64), b.to(torch.float64)
    keep = torch.ones(a.shape, dtype=torch.bool, device=a.device)
    for _ in range(max_rounds):
        iou = float(a[keep].sum()) / max(object_pixels + float(b[keep].sum()), 1e-300)
        new = keep & (a >= min(mask_lambda, iou) * b)
        if torch.equal(new, keep):
            break
        keep = new
    return keep


def drawn_agreement(model: GaussianModel, foreground: Tensor, views: Sequence[View],
                    pixel_labels: Sequence[Tensor], backend: str = "native") -> float:
    """IoU of the ``foreground`` rendered alone and drawn above 0.5 (as the segment stage draws the
    object) with the masks, over every view's judged pixels (labels 0 / 1), leaving out the
    background pixels where the object is hidden in the scene render (the pixels the
    object-render check leaves out)."""
    obj = model.select(torch.nonzero(foreground).squeeze(1))
    values = foreground.to(model.means.dtype)
    inter = union = 0
    for v, lab in zip(views, pixel_labels):
        alone, q = _judged_pixels(model, obj, values, v, lab.to(model.device), backend)
        inter += int((alone & (q == 1)).sum())
        union += int(((alone | (q == 1)) & (q >= 0)).sum())
    return inter / max(union, 1)
