"""The Gaussian scene model: raw parameters, activations, extras and optimizer-safe edits.

Storage (docs/method.md §1), all tensors with a leading dimension N, in one ordered dict:

    means          [N, 3]      float32  world positions
    log_scales     [N, 3]      float32  log of the per-axis standard deviations
    quats          [N, 4]      float32  rotation (w, x, y, z), unnormalised
    opacity_logits [N]         float32  logit of the opacity
    sh0            [N, 1, 3]   float32  DC SH coefficient per colour channel
    shN            [N, K-1, 3] float32  higher SH coefficients, K = (sh_degree + 1)²

plus any number of named **extras** (per-Gaussian mask-label logits, object ids, ...), each
[N, ...] of any dtype, with a fill value used when Gaussians are appended without one.
Float tensors are ``nn.Parameter`` s; whether one trains is decided by which optimizer
owns it (and ``requires_grad``).

Every structural edit (:meth:`GaussianModel.keep`, :meth:`append`, :meth:`replace`) goes
through one routine that rewrites each tensor **and** the per-element state of every
optimizer that owns it (Adam's ``exp_avg`` / ``exp_avg_sq`` are indexed the same way,
appended rows start at zero, the scalar ``step`` is kept), so several optimizers (COB-GS's
label and texture optimizers) stay in sync with the model.
"""

from __future__ import annotations

import re
from typing import Iterable, Mapping, Optional, Sequence

import numpy as np
import torch
from torch import Tensor, nn

from cobgs.errors import InputError, check_shape
from cobgs.gaussians.sh import C0, MAX_DEGREE, num_coeffs, rgb_to_sh0, sh0_to_rgb, sh_to_color

CORE = ("means", "log_scales", "quats", "opacity_logits", "sh0", "shN")
_EXTRA_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")
_ENDS_WITH_INDEX = re.compile(r"_\d+$")
# PLY property names of the standard layout; extras must not collide with them.
_RESERVED_PREFIXES = ("f_dc", "f_rest", "scale", "rot", "opacity", "nx", "ny", "nz", "x", "y", "z")


def inverse_sigmoid(x: Tensor) -> Tensor:
    return torch.log(x / (1.0 - x))


def quat_to_rotmat(quats: Tensor, normalize: bool = True) -> Tensor:
    """Rotation matrices of (w, x, y, z) quaternions (the one copy: the model and the
    rasterizer's reference use it).

    Args:
        quats: [N, 4].
        normalize: normalise them first; False for quaternions already of unit norm (the
            reference, which normalises them itself), so their entries are used as given.

    Returns:
        [N, 3, 3].
    """
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12) if normalize else quats
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        -1,
    ).reshape(q.shape[:-1] + (3, 3))


class GaussianModel:
    """A set of 3D Gaussians (see the module docstring for the storage layout).

    Args:
        means: [N, 3] positions.
        log_scales: [N, 3] log standard deviations.
        quats: [N, 4] (w, x, y, z) rotations.
        opacity_logits: [N] logit opacities.
        sh0: [N, 1, 3] DC coefficients.
        shN: [N, K-1, 3] higher coefficients; K - 1 in {0, 3, 8, 15} fixes ``sh_degree``.
        active_sh_degree: degree used for rendering now (default: ``sh_degree``).
    """

    def __init__(
        self,
        means: Tensor,
        log_scales: Tensor,
        quats: Tensor,
        opacity_logits: Tensor,
        sh0: Tensor,
        shN: Tensor,
        active_sh_degree: Optional[int] = None,
    ):
        n = means.shape[0]
        check_shape("means", means, (n, 3))
        check_shape("log_scales", log_scales, (n, 3))
        check_shape("quats", quats, (n, 4))
        check_shape("opacity_logits", opacity_logits, (n,))
        check_shape("sh0", sh0, (n, 1, 3))
        if shN.dim() != 3 or shN.shape[0] != n or shN.shape[2] != 3:
            raise InputError(f"shN must have shape [{n}, K-1, 3], got {list(shN.shape)}")
        degrees = {num_coeffs(d) - 1: d for d in range(MAX_DEGREE + 1)}
        if shN.shape[1] not in degrees:
            raise InputError(
                f"shN must hold 0, 3, 8 or 15 coefficients (degree 0..3), got {shN.shape[1]}"
            )
        self.sh_degree: int = degrees[shN.shape[1]]
        self.active_sh_degree: int = self.sh_degree if active_sh_degree is None else int(active_sh_degree)
        if not 0 <= self.active_sh_degree <= self.sh_degree:
            raise InputError(f"active_sh_degree must be in 0..{self.sh_degree}, got {active_sh_degree}")
        self.data: dict[str, Tensor] = {}
        self.fill: dict[str, float] = {}
        for name, t in zip(CORE, (means, log_scales, quats, opacity_logits, sh0, shN)):
            self.data[name] = _wrap(t.detach().float().contiguous())

    # -- construction ----------------------------------------------------------------------
    @classmethod
    def from_points(
        cls,
        xyz: Tensor,
        rgb: Optional[Tensor] = None,
        *,
        sh_degree: int = 3,
        init_opacity: float = 0.1,
        active_sh_degree: int = 0,
    ) -> "GaussianModel":
        """3DGS initialisation from a point cloud.

        Scales are isotropic: the root of the mean squared distance to the 3 nearest other
        points (floored at sqrt(1e-7)), so the initial Gaussians roughly tile the cloud.

        Args:
            xyz: [P, 3] points.
            rgb: [P, 3] colours in [0, 1] (default mid-grey).
            sh_degree: maximum SH degree (0..3).
            init_opacity: opacity of every Gaussian.
            active_sh_degree: degree used at first (training raises it on a schedule).
        """
        check_shape("xyz", xyz, (None, 3))
        p = xyz.shape[0]
        if p == 0:
            raise InputError("from_points needs at least one point, got 0")
        if rgb is None:
            rgb = torch.full((p, 3), 0.5)
        check_shape("rgb", rgb, (p, 3))
        xyz = xyz.detach().float().cpu()
        d2 = knn_mean_sq_dist(xyz, k=3).clamp_min(1e-7)
        log_scales = torch.log(torch.sqrt(d2))[:, None].repeat(1, 3)
        quats = torch.zeros(p, 4)
        quats[:, 0] = 1.0
        opac = inverse_sigmoid(torch.full((p,), float(init_opacity)))
        sh0 = rgb_to_sh0(rgb.detach().float().cpu())[:, None, :]
        shN = torch.zeros(p, num_coeffs(sh_degree) - 1, 3)
        return cls(xyz, log_scales, quats, opac, sh0, shN, active_sh_degree=min(active_sh_degree, sh_degree))

    @classmethod
    def random_in_box(
        cls,
        n: int,
        lo: Sequence[float],
        hi: Sequence[float],
        *,
        generator: Optional[torch.Generator] = None,
        sh_degree: int = 3,
        init_opacity: float = 0.1,
        active_sh_degree: int = 0,
    ) -> "GaussianModel":
        """3DGS's initialisation without SfM points: ``n`` uniform points in a box.

        Colours are grey plus a tiny random DC term (as 3DGS's random init for
        NeRF-synthetic); scales come from :meth:`from_points`.
        """
        if n <= 0:
            raise InputError(f"n must be positive, got {n}")
        lo_t, hi_t = torch.tensor(lo, dtype=torch.float32), torch.tensor(hi, dtype=torch.float32)
        xyz = lo_t + torch.rand(n, 3, generator=generator) * (hi_t - lo_t)
        rgb = sh0_to_rgb(torch.rand(n, 3, generator=generator) / 255.0)
        return cls.from_points(
            xyz, rgb, sh_degree=sh_degree, init_opacity=init_opacity, active_sh_degree=active_sh_degree
        )

    # -- basic properties --------------------------------------------------------------------
    def __len__(self) -> int:
        return self.data["means"].shape[0]

    def __getattr__(self, name: str):
        # Raw tensors are reachable as attributes: model.means, model.label_logits, ...
        data = self.__dict__.get("data")
        if data is not None and name in data:
            return data[name]
        raise AttributeError(f"GaussianModel has no attribute {name!r}")

    @property
    def device(self) -> torch.device:
        return self.data["means"].device

    @property
    def extras(self) -> list[str]:
        """Names of the extra per-Gaussian attributes, in insertion order."""
        return [k for k in self.data if k not in CORE]

    @property
    def scales(self) -> Tensor:
        """[N, 3] activated scales (exp of ``log_scales``)."""
        return torch.exp(self.data["log_scales"])

    @property
    def opacities(self) -> Tensor:
        """[N] activated opacities in (0, 1)."""
        return torch.sigmoid(self.data["opacity_logits"])

    @property
    def rotations(self) -> Tensor:
        """[N, 4] unit quaternions."""
        q = self.data["quats"]
        return q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)

    @property
    def sh(self) -> Tensor:
        """[N, K, 3] all SH coefficients (DC first)."""
        return torch.cat([self.data["sh0"], self.data["shN"]], 1)

    def colors(self, camera_center: Tensor, degree: Optional[int] = None, index: Optional[Tensor] = None) -> Tensor:
        """View-dependent RGB per Gaussian, as 3DGS: max(SH(d) + 0.5, 0).

        Args:
            camera_center: [3] camera centre in world coordinates.
            degree: SH degree to use (default ``active_sh_degree``).
            index: optional [M] long indices to evaluate only some Gaussians.

        Returns:
            [N, 3] (or [M, 3]) colours.
        """
        deg = self.active_sh_degree if degree is None else int(degree)
        means, sh0, shN = self.data["means"], self.data["sh0"], self.data["shN"]
        if index is not None:
            means, sh0, shN = means[index], sh0[index], shN[index]
        if deg == 0:
            return (sh0[:, 0, :] * C0 + 0.5).clamp_min(0.0)
        k = num_coeffs(deg)
        coeffs = torch.cat([sh0, shN[:, : k - 1]], 1)
        dirs = means - camera_center.to(means)
        dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        return sh_to_color(deg, coeffs, dirs)

    # -- extras ------------------------------------------------------------------------------
    def add_extra(self, name: str, value: Tensor | float | int, fill: float | int = 0) -> Tensor:
        """Attach a per-Gaussian attribute.

        Args:
            name: identifier (letters, digits, underscores; not ending in ``_<digits>``,
                which the PLY layout reserves for vector components; not a standard
                3DGS property name).
            value: [N, ...] tensor, or a scalar broadcast to [N].
            fill: value of the attribute for Gaussians appended without one (e.g. the
                children of a split).

        Returns:
            the stored tensor (an ``nn.Parameter`` for floating dtypes).
        """
        check_extra_name(name)
        if name in self.data:
            raise InputError(f"extra {name!r} already exists (use set_tensor to change it)")
        n = len(self)
        if not isinstance(value, Tensor):
            value = torch.full((n,), value, dtype=torch.float32 if isinstance(value, float) else torch.int64)
        if value.dim() == 0 or value.shape[0] != n:
            raise InputError(f"extra {name!r} must have leading size {n}, got {list(value.shape)}")
        self.data[name] = _wrap(value.detach().to(self.device).contiguous())
        self.fill[name] = fill
        return self.data[name]

    def remove_extra(self, name: str) -> None:
        if name in CORE or name not in self.data:
            raise InputError(f"{name!r} is not an extra of this model (extras: {self.extras})")
        del self.data[name]
        self.fill.pop(name, None)

    def set_tensor(self, name: str, value: Tensor, optimizers: Iterable = (), reset_state: bool = True) -> Tensor:
        """Replace one tensor's values (same shape), e.g. the 3DGS opacity reset.

        The optimizers that own the old parameter are pointed at the new one; with
        ``reset_state`` their per-element moments are zeroed (3DGS does this for opacity).
        """
        old = self.data[name]
        check_shape(name, value, tuple(old.shape))
        new = _wrap(value.detach().to(old).contiguous(), old.requires_grad)
        for opt in optimizers:
            _swap_param(opt, old, new, lambda s: torch.zeros_like(s) if reset_state else s)
        self.data[name] = new
        return new

    # -- structural edits --------------------------------------------------------------------
    def keep(self, mask: Tensor, optimizers: Iterable = ()) -> None:
        """Keep the Gaussians where ``mask`` [N] bool is True (prune the rest), in place."""
        self._edit(_as_index(mask, len(self)), None, optimizers)

    def append(self, new: Mapping[str, Tensor], optimizers: Iterable = ()) -> None:
        """Append Gaussians given as ``{name: [M, ...]}``, in place.

        Core tensors are required; missing extras take their fill value. Optimizer moments
        of the new rows start at zero.
        """
        self._edit(None, new, optimizers)

    def replace(self, remove: Tensor, new: Mapping[str, Tensor], optimizers: Iterable = ()) -> None:
        """Remove the Gaussians where ``remove`` [N] bool is True and append ``new``.

        The building block of splitting (remove parents, append children) and of any
        other refinement that swaps Gaussians for others.
        """
        keep = _as_index(~_as_bool(remove, len(self)), len(self))
        self._edit(keep, new, optimizers)

    def _edit(self, keep_idx: Optional[Tensor], new: Optional[Mapping[str, Tensor]], optimizers) -> None:
        optimizers = list(optimizers)
        rows = self._complete(new) if new is not None else None
        for name in list(self.data):
            old = self.data[name]
            t = old.detach()
            if keep_idx is not None:
                t = t[keep_idx]
            m = 0
            if rows is not None:
                add = rows[name]
                m = add.shape[0]
                t = torch.cat([t, add], 0)
            p = _wrap(t.contiguous(), old.requires_grad)

            def fix(s, keep_idx=keep_idx, m=m):
                if keep_idx is not None:
                    s = s[keep_idx]
                if m:
                    s = torch.cat([s, s.new_zeros((m,) + s.shape[1:])], 0)
                return s

            for opt in optimizers:
                _swap_param(opt, old, p, fix)
            self.data[name] = p

    def _complete(self, new: Mapping[str, Tensor]) -> dict[str, Tensor]:
        unknown = sorted(set(new) - set(self.data))
        if unknown:
            raise InputError(f"unknown tensors {unknown} (model has {list(self.data)})")
        missing = [k for k in CORE if k not in new]
        if missing:
            raise InputError(f"new Gaussians lack core tensors {missing}")
        m = new["means"].shape[0]
        out = {}
        for name, old in self.data.items():
            if name in new:
                t = new[name].detach().to(device=old.device, dtype=old.dtype)
                if tuple(t.shape) != (m,) + tuple(old.shape[1:]):
                    raise InputError(
                        f"new {name} must have shape {[m] + list(old.shape[1:])}, got {list(t.shape)}"
                    )
            else:
                t = torch.full((m,) + tuple(old.shape[1:]), self.fill.get(name, 0), dtype=old.dtype, device=old.device)
            out[name] = t
        return out

    # -- new Gaussians from existing ones ----------------------------------------------------
    def gather(self, index: Tensor) -> dict[str, Tensor]:
        """Detached copies of the rows ``index`` ([M] long or [N] bool) of every tensor."""
        idx = _as_index(index, len(self)) if index.dtype == torch.bool else index
        return {k: v.detach()[idx].clone() for k, v in self.data.items()}

    def split_children(
        self,
        index: Tensor,
        n_children: int = 2,
        scale_divisor: float = 1.6,
        reset: Sequence[str] = (),
        generator: Optional[torch.Generator] = None,
    ) -> dict[str, Tensor]:
        """Children of the Gaussians ``index``, sampled as in the 3DGS split.

        Each child's mean is ``mu + R (s * eps)``, eps ~ N(0, I) (a sample of the parent
        Gaussian), its scale is ``s / scale_divisor`` and every other tensor is copied,
        except the extras named in ``reset`` which take their fill value (COB-GS resets
        the label logit of split children to 0).

        Args:
            index: [M] long or [N] bool parents.
            n_children: children per parent.
            scale_divisor: 1.6 in 3DGS (0.8 x 2) and COB-GS.
            reset: extras to set to their fill value in the children.
            generator: RNG for the position samples.

        Returns:
            ``{name: [M * n_children, ...]}`` children ordered child-major
            (all first children, then all second children), ready for :meth:`replace`.
        """
        rows = self.gather(index)
        out = {k: v.repeat((n_children,) + (1,) * (v.dim() - 1)) for k, v in rows.items()}
        s = torch.exp(rows["log_scales"]).repeat(n_children, 1)
        eps = torch.randn(s.shape, generator=generator, device="cpu").to(s)
        R = quat_to_rotmat(rows["quats"]).repeat(n_children, 1, 1)
        out["means"] = out["means"] + (R @ (s * eps)[..., None])[..., 0]
        out["log_scales"] = torch.log(s / scale_divisor)
        for name in reset:
            if name not in self.fill:
                raise InputError(f"cannot reset {name!r}: not an extra (extras: {self.extras})")
            out[name] = torch.full_like(out[name], self.fill[name])
        return out

    def select(self, index: Tensor) -> "GaussianModel":
        """A new, independent model with the Gaussians ``index`` ([M] long or [N] bool)."""
        rows = self.gather(index)
        out = GaussianModel(*(rows[k] for k in CORE), active_sh_degree=self.active_sh_degree)
        for name in self.extras:
            out.data[name] = _wrap(rows[name])
            out.fill[name] = self.fill.get(name, 0)
        return out

    def clone(self) -> "GaussianModel":
        return self.select(torch.arange(len(self), device=self.device))

    def to(self, device) -> "GaussianModel":
        """Move every tensor (returns self; optimizers must be rebuilt afterwards)."""
        for k, v in list(self.data.items()):
            self.data[k] = _wrap(v.detach().to(device), v.requires_grad)
        return self

    # -- optimizers and checkpoints ----------------------------------------------------------
    def parameters(self, names: Optional[Iterable[str]] = None) -> list[Tensor]:
        names = list(self.data) if names is None else list(names)
        return [self.data[n] for n in names]

    def make_adam(self, lrs: Mapping[str, float], eps: float = 1e-15, fused: bool = True) -> torch.optim.Adam:
        """Adam with one parameter group per tensor name (group key ``"name"``).

        Args:
            lrs: tensor name → learning rate; only these tensors are optimised.
            eps: Adam epsilon (1e-15 in 3DGS and COB-GS).
            fused: use PyTorch's fused kernel (same update rule; about 2.5x faster than
                the multi-tensor path on CPU for 100k Gaussians).
        """
        groups = []
        for name, lr in lrs.items():
            if name not in self.data:
                raise InputError(f"no tensor named {name!r} to optimise (have {list(self.data)})")
            p = self.data[name]
            if not p.is_floating_point():
                raise InputError(f"tensor {name!r} has dtype {p.dtype} and cannot be optimised")
            groups.append({"params": [p], "lr": float(lr), "name": name})
        return torch.optim.Adam(groups, lr=0.0, eps=eps, fused=fused)

    def state_dict(self) -> dict:
        return {
            "tensors": {k: v.detach().clone() for k, v in self.data.items()},
            "fill": dict(self.fill),
            "active_sh_degree": self.active_sh_degree,
        }

    @classmethod
    def from_state_dict(cls, state: Mapping) -> "GaussianModel":
        t = state["tensors"]
        m = cls(*(t[k] for k in CORE), active_sh_degree=state["active_sh_degree"])
        for name, v in t.items():
            if name not in CORE:
                m.data[name] = _wrap(v.clone())
                m.fill[name] = state["fill"].get(name, 0)
        return m

    def __repr__(self) -> str:
        return (
            f"GaussianModel(N={len(self)}, sh_degree={self.sh_degree}, "
            f"active_sh_degree={self.active_sh_degree}, extras={self.extras})"
        )


def check_extra_name(name: str) -> None:
    """Raise :class:`InputError` unless ``name`` can be an extra (and a PLY property)."""
    if not isinstance(name, str) or not _EXTRA_NAME.match(name):
        raise InputError(f"extra name must match [A-Za-z][A-Za-z0-9_]*, got {name!r}")
    if _ENDS_WITH_INDEX.search(name):
        raise InputError(f"extra name {name!r} must not end in _<digits> (reserved for vector components)")
    if name in CORE or any(name == p or name.startswith(p + "_") for p in _RESERVED_PREFIXES):
        raise InputError(f"extra name {name!r} collides with a standard 3DGS tensor or PLY property")


def knn_mean_sq_dist(xyz: Tensor, k: int = 3) -> Tensor:
    """Mean squared distance of each point to its ``k`` nearest other points.

    Args:
        xyz: [P, 3].

    Returns:
        [P] float32 (0 where there are no other points).
    """
    from scipy.spatial import cKDTree

    pts = xyz.detach().cpu().double().numpy()
    p = pts.shape[0]
    if p < 2:
        return torch.zeros(p)
    kk = min(k, p - 1)
    d, _ = cKDTree(pts).query(pts, k=kk + 1)
    d = np.asarray(d).reshape(p, kk + 1)[:, 1:]  # column 0 is the point itself
    return torch.from_numpy((d**2).mean(1)).float()


def _wrap(t: Tensor, requires_grad: bool = True) -> Tensor:
    if t.is_floating_point():
        return nn.Parameter(t, requires_grad=requires_grad)
    return t


def _as_bool(mask: Tensor, n: int) -> Tensor:
    if mask.dtype != torch.bool or mask.shape != (n,):
        raise InputError(f"mask must be a bool tensor of shape [{n}], got {mask.dtype} {list(mask.shape)}")
    return mask


def _as_index(mask: Tensor, n: int) -> Tensor:
    return torch.nonzero(_as_bool(mask, n), as_tuple=False)[:, 0]


def _swap_param(opt: torch.optim.Optimizer, old: Tensor, new: Tensor, fix) -> None:
    """Point ``opt`` at ``new`` instead of ``old`` and transform its per-element state."""
    for group in opt.param_groups:
        for i, p in enumerate(group["params"]):
            if p is old:
                group["params"][i] = new
                state = opt.state.pop(old, None)
                if state is not None:
                    opt.state[new] = {
                        k: (fix(v) if isinstance(v, Tensor) and v.dim() > 0 and v.shape == old.shape else v)
                        for k, v in state.items()
                    }
                return


def gaussian_lrs(config, position_lr: float, extent: float) -> dict:
    """The 3DGS learning rate of every Gaussian tensor, one table for the baseline training
    and COB-GS's texture stages: ``config`` has ``sh0_lr``, ``shN_lr``, ``opacity_lr``,
    ``scaling_lr`` and ``rotation_lr`` (:class:`~cobgs.configs.TrainConfig`,
    :class:`~cobgs.configs.RefineConfig`); the position lr is scaled by the scene extent."""
    return {"means": position_lr * extent, "sh0": config.sh0_lr, "shN": config.shN_lr,
            "opacity_logits": config.opacity_lr, "log_scales": config.scaling_lr, "quats": config.rotation_lr}

