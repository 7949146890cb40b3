"""Adam that steps only the Gaussians a view touches (``TrainConfig.sparse_adam``).

Standard Adam moves every parameter at every step: a Gaussian outside the view has zero
gradient, yet its first moment keeps moving it (and both moments decay). A selective step
(as gsplat's ``SelectiveAdam``) updates the rows of the visible Gaussians only; the others
keep their parameters and moments until a view sees them. The bias correction uses the
group's global step, as gsplat's does.

The state has Adam's layout (``step``, ``exp_avg``, ``exp_avg_sq`` per parameter), so the
model's structural edits (clone / split / prune, :mod:`cobgs.gaussians.model`), checkpoints
and the exported moments (:mod:`cobgs.train.adam_moments`) work unchanged.
"""

from __future__ import annotations

import math
from typing import Mapping, Optional

import torch
from torch import Tensor

from cobgs.errors import InputError


class VisibleAdam(torch.optim.Optimizer):
    """Adam over one tensor per group whose rows are Gaussians; :meth:`step` takes the
    visible rows (``visible``: bool [N]); without it every row steps, as in Adam."""

    def __init__(self, groups, lr: float = 1e-3, betas=(0.9, 0.999), eps: float = 1e-15):
        super().__init__(groups, {"lr": lr, "betas": betas, "eps": eps})

    @classmethod
    def for_model(cls, model, lrs: Mapping[str, float], eps: float = 1e-15) -> "VisibleAdam":
        """One named group per tensor, as :meth:`GaussianModel.make_adam` builds them."""
        groups = []
        for name, lr in lrs.items():
            if name not in model.data:
                raise InputError(f"no tensor named {name!r} to optimise (have {list(model.data)})")
            groups.append({"params": [model.data[name]], "lr": float(lr), "name": name})
        return cls(groups, eps=eps)

    @torch.no_grad()
    def step(self, closure=None, visible: Optional[Tensor] = None):  # type: ignore[override]
        idx = None if visible is None else torch.nonzero(visible, as_tuple=False)[:, 0]
        for group in self.param_groups:
            b1, b2 = group["betas"]
            for p in group["params"]:
                if p.grad is None:
                    continue
                st = self.state[p]
                if not st:
                    st["step"] = torch.zeros((), dtype=torch.float32)
                    st["exp_avg"] = torch.zeros_like(p)
                    st["exp_avg_sq"] = torch.zeros_like(p)
                st["step"] += 1
                t = float(st["step"])
                step_size = group["lr"] / (1.0 - b1 ** t)
                root_bc2 = math.sqrt(1.0 - b2 ** t)
                ea, eas, g = st["exp_avg"], st["exp_avg_sq"], p.grad
                if idx is None:
                    ea.mul_(b1).add_(g, alpha=1.0 - b1)
                    eas.mul_(b2).addcmul_(g, g, value=1.0 - b2)
                    p.addcdiv_(ea, eas.sqrt().div_(root_bc2).add_(group["eps"]), value=-step_size)
                    continue
                if idx.numel() == 0:
                    continue
                gv = g.index_select(0, idx)
                m = ea.index_select(0, idx).mul_(b1).add_(gv, alpha=1.0 - b1)
                v = eas.index_select(0, idx).mul_(b2).addcmul_(gv, gv, value=1.0 - b2)
                ea.index_copy_(0, idx, m)
                eas.index_copy_(0, idx, v)
                pv = p.index_select(0, idx).addcdiv_(m, v.sqrt().div_(root_bc2).add_(group["eps"]), value=-step_size)
                p.index_copy_(0, idx, pv)
        return None


__all__ = ["VisibleAdam"]
