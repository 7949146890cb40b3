"""NG-GS's boundary stage (NeRF-Guided 3D Gaussian Splatting Segmentation, CVPR 2026), rule
for rule as its released code runs it (BJTU-KD3D/NG-GS ``scene/ngs_model.py``, ``train.py``;
docs/method.md §3 "NG-GS"), in this project's own code.

NG-GS is COB-GS's released refinement plus one loss in the TEXTURE stages (``--use_ngs``):

* **Which Gaussians.** Every texture iteration picks the top ``max_points`` (4096) Gaussians
  by a boundary score: ``4 p (1 − p)`` of the mask label ``p = sigmoid(logit)``, plus
  ``1 − accum / max(accum)`` of the mask-signal accumulator where it holds anything (the
  released code's accumulator is reset by every split, so in the texture stages it is zero and
  the label term decides); with no score at all, a random subset.
* **The refiner.** A multi-resolution hash encoding of their positions (8 levels × 2
  features, 2^15 entries per level, resolution 16 → 512 growing geometrically, hash
  ``(x·1540863) ^ (y·1251391) ^ (z·1987613) mod 2^15`` of the floored grid coordinates;
  positions normalised to the selected points' bounding box) and their DC colour go through a
  64-wide two-layer MLP whose features are modulated by FiLM on the colour; it predicts a
  refined colour ``base + 0.1 tanh(·)`` and a softplus density.
* **The loss.** ``λ_align · align + λ_cont · cont + λ_smooth · smooth + 1e-3 · mean density``:
  ``align`` = MSE(refined, RBF interpolation of the base colours over the 8 nearest neighbours,
  σ = their mean distance, detached) + 0.25 · MSE(base, refined detached); ``cont`` = the
  RBF-weighted squared colour difference to the neighbours (mean over point-neighbour pairs); ``smooth`` = MSE(refined, the
  refiner's colour at positions jittered by 1 % of the points' spread).
* **What trains.** The refiner (its own Adam, lr 1e-3, eps 1e-15, stepped with the scene's
  texture Adam) and, through the loss, the selected Gaussians' DC colours and positions (the
  latter through the continuity term's RBF weights only: the encoding floors positions to
  table indices); the texture Adam steps them with everything else. Nothing of the MASK
  stages changes.

Randomness (initialisation, jitter, the random subset) comes from private generators seeded
by ``NGSConfig.seed``, so a run repeats.
"""

from __future__ import annotations

import math
from typing import Optional

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from cobgs.configs import NGSConfig
from cobgs.gaussians.sh import C0

#: The primes of the released spatial hash (one per axis).
PRIMES = (1_540_863, 1_251_391, 1_987_613)


class HashEncoding(nn.Module):
    """Multi-resolution hash encoding of 3D points (module docstring)."""

    def __init__(self, levels: int = 8, features_per_level: int = 2, log2_hashmap_size: int = 15,
                 base_resolution: int = 16, finest_resolution: int = 512, generator: Optional[torch.Generator] = None):
        super().__init__()
        self.levels, self.features_per_level = levels, features_per_level
        self.hashmap_size = 2 ** log2_hashmap_size
        self.base_resolution, self.finest_resolution = base_resolution, finest_resolution
        self.per_level_scale = (math.exp((math.log(finest_resolution) - math.log(base_resolution)) / (levels - 1))
                                if levels > 1 else 1.0)
        self.tables = nn.ParameterList()
        for _ in range(levels):
            w = torch.empty(self.hashmap_size, features_per_level).uniform_(-1e-4, 1e-4, generator=generator)
            self.tables.append(nn.Parameter(w))

    @property
    def out_dim(self) -> int:
        return self.levels * self.features_per_level

    def resolution(self, level: int) -> int:
        """The grid resolution of ``level``: ``int(base · scale^level)``, within [1, finest]."""
        r = int(self.base_resolution * (self.per_level_scale ** level))
        return max(1, min(r, self.finest_resolution))

    def hash(self, coords: Tensor) -> Tensor:
        """Table index of integer grid coordinates [..., 3]."""
        x, y, z = coords.unbind(-1)
        return torch.remainder((x * PRIMES[0]) ^ (y * PRIMES[1]) ^ (z * PRIMES[2]), self.hashmap_size)

    @staticmethod
    def normalize(xyz: Tensor) -> Tensor:
        """Positions in the points' own bounding box, [0, 1] per axis (the box detached)."""
        lo = xyz.detach().amin(dim=0, keepdim=True)
        hi = xyz.detach().amax(dim=0, keepdim=True)
        return ((xyz - lo) / (hi - lo).clamp_min(1e-6)).clamp(0.0, 1.0)

    def forward(self, xyz: Tensor) -> Tensor:
        unit = self.normalize(xyz)
        out = []
        for level, table in enumerate(self.tables):
            coords = torch.floor(unit * self.resolution(level)).long()
            out.append(table[self.hash(coords)])
        return torch.cat(out, dim=-1)


class BoundaryRefiner(nn.Module):
    """The refiner MLP with FiLM on the base colour (module docstring)."""

    def __init__(self, config: NGSConfig):
        super().__init__()
        self.config = c = config
        g = torch.Generator().manual_seed(c.seed)
        with torch.random.fork_rng(devices=[]):  # the Linear layers' default init, seeded
            torch.manual_seed(c.seed + 1)
            self.encoder = HashEncoding(c.hash_levels, c.features_per_level, c.log2_hashmap_size,
                                        c.base_resolution, c.finest_resolution, generator=g)
            self.trunk = nn.Sequential(nn.Linear(self.encoder.out_dim + 3, c.hidden_dim), nn.ReLU(),
                                       nn.Linear(c.hidden_dim, c.hidden_dim), nn.ReLU())
            self.film = nn.Linear(3, 2 * c.hidden_dim)
            self.rgb_head = nn.Linear(c.hidden_dim, 3)
            self.density_head = nn.Linear(c.hidden_dim, 1)

    def forward(self, xyz: Tensor, base_rgb: Tensor) -> tuple[Tensor, Tensor]:
        h = self.trunk(torch.cat([self.encoder(xyz), base_rgb], dim=-1))
        gamma, beta = self.film(base_rgb).chunk(2, dim=-1)
        h = F.relu((1.0 + gamma) * h + beta)
        rgb = (base_rgb + 0.1 * torch.tanh(self.rgb_head(h))).clamp(0.0, 1.0)
        return rgb, F.softplus(self.density_head(h))


def boundary_scores(label_logits: Tensor, accum: Optional[Tensor] = None) -> Tensor:
    """``4 p (1 − p)`` of the labels, plus ``1 − accum / max(accum)`` where the mask-signal
    accumulator holds anything (max > 0)."""
    p = torch.sigmoid(label_logits.detach().reshape(-1))
    score = 4.0 * p * (1.0 - p)
    if accum is not None and accum.numel() == score.numel():
        a = accum.detach().reshape(-1).to(score)
        if bool(torch.isfinite(a).any()) and float(a.max()) > 0:
            score = score + 1.0 - (a / a.max().clamp_min(1e-6)).clamp(0.0, 1.0)
    return score


def boundary_indices(scores: Tensor, max_points: int, generator: Optional[torch.Generator] = None) -> Tensor:
    """The top ``max_points`` Gaussians by score; a random subset where no score is > 0."""
    n = scores.numel()
    keep = min(n, max_points)
    if n == 0 or float(scores.max()) <= 0:
        return torch.randperm(n, generator=generator, device="cpu")[:keep].to(scores.device)
    return torch.topk(scores, keep, largest=True).indices


def rbf_interpolate(xyz: Tensor, values: Tensor, k_neighbors: int = 8) -> tuple[Tensor, Tensor]:
    """RBF interpolation of ``values`` at each point from its ``k_neighbors`` nearest others
    (weights ``exp(−d² / 2σ²)``, σ = the mean neighbour distance, detached; normalised), and
    the continuity term: the weighted squared difference to each neighbour, summed over
    channels, averaged over every (point, neighbour) pair (the released ``.sum(-1).mean()``)."""
    if xyz.shape[0] < 2:
        return values, values.new_zeros(())
    k = min(k_neighbors + 1, xyz.shape[0])
    d, idx = torch.topk(torch.cdist(xyz, xyz), k=k, largest=False)
    d, idx = d[:, 1:], idx[:, 1:]  # the point itself first
    neigh = values[idx]
    sigma = d.detach().mean().clamp_min(1e-4)
    w = torch.exp(-(d ** 2) / (2.0 * sigma ** 2))
    w = w / w.sum(dim=-1, keepdim=True).clamp_min(1e-6)
    interp = (w.unsqueeze(-1) * neigh).sum(dim=1)
    cont = (w.unsqueeze(-1) * (values.unsqueeze(1) - neigh).pow(2)).sum(dim=-1).mean()
    return interp, cont


class NGSStage:
    """The NG-GS loss of one refinement: the refiner, its Adam and its generators. Call
    :meth:`loss` in a texture iteration (before ``backward``) and :meth:`step` after the
    texture optimizer's step."""

    def __init__(self, config: NGSConfig, device: torch.device):
        self.config = config
        self.refiner = BoundaryRefiner(config).to(device)
        self.optimizer = torch.optim.Adam(self.refiner.parameters(), lr=config.lr, eps=1e-15)
        self.rng = torch.Generator().manual_seed(config.seed + 2)
        self.last: dict = {}

    def loss(self, model, label_name: str, accum: Optional[Tensor] = None) -> Tensor:
        c = self.config
        idx = boundary_indices(boundary_scores(model.data[label_name], accum), c.max_points, self.rng)
        if idx.numel() == 0:
            return model.data["means"].sum() * 0.0
        xyz = model.data["means"][idx]
        base = (model.data["sh0"][idx, 0, :] * C0 + 0.5).clamp(0.0, 1.0)
        refined, density = self.refiner(xyz, base)
        rbf, cont = rbf_interpolate(xyz, base, c.k_neighbors)
        align = F.mse_loss(refined, rbf.detach()) + 0.25 * F.mse_loss(base, refined.detach())
        eps = xyz.detach().std(dim=0).mean().clamp_min(1e-4) * 0.01
        noise = torch.randn(xyz.shape, generator=self.rng, dtype=xyz.dtype).to(xyz.device)
        smooth_rgb, _ = self.refiner(xyz + noise * eps, base.detach())
        smooth = F.mse_loss(refined, smooth_rgb)
        total = c.lambda_align * align + c.lambda_cont * cont + c.lambda_smooth * smooth + 1e-3 * density.mean()
        self.last = {"align": float(align.detach()), "cont": float(cont.detach()), "smooth": float(smooth.detach()),
                     "points": int(idx.numel())}
        return total

    def step(self) -> None:
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)


__all__ = ["BoundaryRefiner", "HashEncoding", "NGSStage", "PRIMES", "boundary_indices", "boundary_scores",
           "rbf_interpolate"]
