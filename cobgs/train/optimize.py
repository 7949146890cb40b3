"""Baseline 3DGS optimisation (docs/method.md §1): the scene COB-GS later refines.

Recipe: 0.8·L1 + 0.2·(1 − SSIM); Adam (eps 1e-15) with per-tensor learning rates and an
exponentially decaying position lr scaled by the scene extent; SH degree raised on a
schedule; densification (clone small / split large Gaussians whose accumulated view-space
gradient, in NDC units, exceeds 2e-4), pruning of transparent and oversized Gaussians,
periodic opacity reset.

**Schedules for short runs.** The iteration-valued fields of :class:`TrainConfig` (its
``*_its`` fields) are written for the reference length ``reference_iterations`` (30k, as
in the paper). With ``scale_schedule=True`` each *phase boundary and period* is
multiplied by ``iterations / reference_iterations`` (rounded, at least 1), so a 7k run
performs the whole recipe compressed — densify from 117 to 3500, opacity reset every 700,
SH degree +1 every 233, position lr decayed fully by iteration 7000. The densification
*interval* is not scaled (unless ``scale_densify_interval``): it sets how many views the
gradient statistic averages before each clone/split decision, and scaling it multiplied
the number of densification rounds (fern 1/8: 327k Gaussians after 950 of 7000
iterations with a 23-iteration interval). With ``scale_schedule=False`` the 30k schedule
runs as written and simply stops early (3DGS's "7k checkpoint").
:meth:`TrainConfig.schedule` returns the resolved numbers.

Differences from the released 3DGS code, both deliberate and documented: the optimizer
step of a densification iteration is taken *before* the densification (3DGS drops that
iteration's gradients when it rebuilds its tensors); the screen-space size pruning is off
by default (in the released code it never fires because its radii statistic is zeroed by
the clone step just before; gsplat disables it too).

**Recipes** (``TrainConfig.recipe``, docs/method.md §1 "Recipes"): ``"3dgs"`` is the above
as the paper runs it; ``"fast"`` turns on a DashGaussian-style resolution schedule
(:meth:`Trainer.downscale`), a Taming-3DGS-style Gaussian budget with score-ranked
densification (:meth:`Trainer.budget_now`) and a shorter schedule (:data:`cobgs.configs.FAST_RECIPE`);
selective Adam (:mod:`cobgs.train.visible_adam`) is a further switch. The 3dgs path is
unchanged by them: its runs are bit-identical to those before the switches existed.

Determinism: one seed drives the initialisation, the view order and the split samples
through private ``torch.Generator`` s; a checkpoint stores them with the model, the Adam
state and the densification statistics, so a resumed run continues bit-identically.
"""

from __future__ import annotations

from collections.abc import Mapping
import dataclasses
import io
import math
import os
import pickle
import resource
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional, Sequence

import torch
from torch import Tensor

from cobgs._atomic import write_bytes_atomic
from cobgs.memory import retain_freed_memory
from cobgs.train.adam_moments import export_moments
from cobgs.data.scene import Scene, View
from cobgs.configs import TrainConfig
from cobgs.errors import DataError, DivergenceError, InputError
from cobgs.gaussians.model import GaussianModel, gaussian_lrs, inverse_sigmoid
from cobgs.train.losses import photometric_loss
from cobgs.evaluate.metrics import psnr as psnr_metric
from cobgs.evaluate.metrics import ssim as ssim_metric
from cobgs.render.image import render

CHECKPOINT_VERSION = 1


@dataclass
class TrainResult:
    """What :func:`train` returns.

    Attributes:
        model: the trained Gaussians.
        iterations: iterations done in total (including before a resume).
        history: one dict per logged iteration: ``it``, ``loss``, ``psnr`` (training view),
            ``num_gaussians``.
        eval: held-out metrics: ``psnr``, ``ssim`` (means over views), ``per_view``
            (name → {psnr, ssim}); empty without test views.
        wall_s: wall time of the optimisation loop (this call).
        s_per_it: ``wall_s`` / iterations done in this call.
        peak_rss_bytes: peak resident memory of the process so far.
        adam_moments: the optimizer's final Adam state per tensor
            (:func:`cobgs.train.adam_moments.export_moments`): what COB-GS's texture stages
            continue from (``refine(..., texture_moments=...)``).
        budget: the Gaussian budget the run kept to (0: none; :meth:`TrainConfig.budget_for`).
    """

    model: GaussianModel
    iterations: int
    history: list[dict] = field(default_factory=list)
    eval: dict = field(default_factory=dict)
    wall_s: float = 0.0
    s_per_it: float = 0.0
    peak_rss_bytes: int = 0
    adam_moments: dict = field(default_factory=dict)
    budget: int = 0
    stopped_at: int = 0  # the iteration a loss plateau ended the run at (TrainConfig.stop_at_plateau), 0: none




def spectral_energy_kept(images: Sequence[Tensor], downscales: Sequence[float]) -> list[float]:
    """For each downscale d, the share of the images' spectral energy (luminance, mean
    removed) at frequencies a 1/d render can hold: ``|f_x|, |f_y| <= 0.5 / d`` cycles per pixel
    (the rendered image's Nyquist band). DashGaussian's measure of how much of the images a
    resolution can fit."""
    import numpy as np

    total = np.zeros(len(downscales))
    whole = 0.0
    for img in images:
        g = img.detach().float().cpu().mean(-1).numpy()
        g = g - g.mean()
        p = np.abs(np.fft.rfft2(g)) ** 2
        fy = np.abs(np.fft.fftfreq(g.shape[0]))[:, None]
        fx = np.fft.rfftfreq(g.shape[1])[None, :]
        whole += float(p.sum())
        for k, d in enumerate(downscales):
            total[k] += float(p[(fy <= 0.5 / d) & (fx <= 0.5 / d)].sum())
    return [float(t / whole) if whole > 0 else 1.0 for t in total]


def resolution_levels(images: Sequence[Tensor], max_downscale: float) -> list[tuple[float, float]]:
    """``(downscale, energy kept)`` for downscales from ``max_downscale`` to 1 in steps of 0.25
    (largest first), from :func:`spectral_energy_kept` of up to 8 of the images."""
    steps = max(0, int(math.floor((max_downscale - 1.0) / 0.25)))
    ds = [1.0 + 0.25 * k for k in range(steps, -1, -1)]
    sample = list(images)[:: max(1, len(images) // 8)][:8]
    kept = spectral_energy_kept(sample, ds)
    # monotone in d by construction; clamp the rounding of the last level
    return [(d, min(1.0, e)) for d, e in zip(ds, kept)]


class StepInfo(Mapping):
    """What one training step returns: ``loss`` and ``psnr`` (floats), ``image``, ``resolution``.
    The loss and the MSE stay on the device until a float is asked for (or :meth:`read`), so a
    CUDA step waits on no host synchronisation unless somebody looks."""

    _KEYS = ("loss", "psnr", "image", "resolution")

    def __init__(self, loss: Tensor, mse: Tensor, image: Tensor, resolution: tuple[int, int]):
        self.loss_tensor, self._mse = loss, mse
        self._values = {"image": image, "resolution": resolution}

    def read(self) -> "StepInfo":
        if "loss" not in self._values:
            mse = float(self._mse)
            self._values["loss"] = float(self.loss_tensor)
            self._values["psnr"] = 10.0 * math.log10(1.0 / max(mse, 1e-12))
        return self

    def __getitem__(self, key: str):
        if key in ("loss", "psnr"):
            self.read()
        return self._values[key]

    def __iter__(self):
        return iter(self._KEYS)

    def __len__(self) -> int:
        return len(self._KEYS)


def expon_lr(step: int, lr_init: float, lr_final: float, max_steps: int) -> float:
    """Log-linear interpolation from ``lr_init`` (step 0) to ``lr_final`` (``max_steps``)."""
    t = min(max(step / max_steps, 0.0), 1.0)
    return math.exp(math.log(lr_init) * (1.0 - t) + math.log(lr_final) * t)


def initial_model(scene: Scene, config: TrainConfig, generator: torch.Generator) -> GaussianModel:
    """SfM points when the scene has them, else ``random_init_points`` in a box.

    The box is the scene's ``init_bounds`` (NeRF-synthetic: the 3DGS cube) or, failing
    that, a cube of half-size ``extent`` around the mean camera centre.
    """
    if scene.points is not None and len(scene.points) > 0:
        return GaussianModel.from_points(
            scene.points, scene.points_rgb, sh_degree=config.sh_degree, init_opacity=config.init_opacity
        )
    if scene.init_bounds is not None:
        lo, hi = scene.init_bounds
    else:
        c = torch.stack([v.camera.center for v in scene.train]).mean(0)
        lo = (c - scene.extent).tolist()
        hi = (c + scene.extent).tolist()
    return GaussianModel.random_in_box(
        config.random_init_points, lo, hi, generator=generator,
        sh_degree=config.sh_degree, init_opacity=config.init_opacity,
    )


class Trainer:
    """The optimisation state of one run; :func:`train` drives it.

    Holds the model, its Adam optimizer, the densification statistics (per Gaussian:
    accumulated NDC gradient norm, visibility count, max screen radius), the iteration,
    the view queue and the RNGs; :meth:`state_dict` / :meth:`load_state_dict` capture
    all of it for exact resumption.
    """

    def __init__(self, scene: Scene, config: TrainConfig = TrainConfig(), model: Optional[GaussianModel] = None):
        if not scene.train:
            raise InputError("the scene has no training views")
        retain_freed_memory()  # process-wide: see cobgs/memory.py
        self.scene = scene
        self.config = config
        self.sched = config.schedule()
        self.extent = float(scene.extent)
        bg = config.background if config.background is not None else scene.background
        self.background = torch.tensor(bg if bg is not None else (0.0, 0.0, 0.0), dtype=torch.float32)
        self.white_background = bool(torch.all(self.background == 1.0))
        self.view_rng = torch.Generator().manual_seed(config.seed)
        self.split_rng = torch.Generator().manual_seed(config.seed + 1)
        init_rng = torch.Generator().manual_seed(config.seed + 2)
        self.bg_rng = torch.Generator().manual_seed(config.seed + 3)
        # layouts whose images are always RGBA composited on ``Scene.background`` (cobgs.data.formats;
        # ``transforms`` scenes may be opaque photographs or RGBA: the user decides)
        from cobgs.data.formats import FORMATS

        if config.random_background and scene.kind in FORMATS and FORMATS[scene.kind].composited:
            raise InputError(
                f"TrainConfig.random_background needs opaque photographs, but this {scene.kind!r} scene's "
                f"images were composited on the fixed background {tuple(scene.background)}: "
                "train it with random_background=False"
            )
        # The device of the scene's images (cobgs.render.image moves each camera to the model's).
        self.device = scene.train[0].image.device
        model = model if model is not None else initial_model(scene, config, init_rng)
        self.model = model.to(self.device) if model.device != self.device else model
        self.optimizer = self._make_optimizer()
        self.iteration = 0
        self.view_queue: list[int] = []
        self._reset_stats()
        cam0 = scene.train[0].camera
        self._n_init = len(self.model)
        #: the Gaussian budget (0: none; TrainConfig.budget_for, from the pixels and the initial count)
        self.budget = config.budget_for(int(cam0.width), int(cam0.height), self._n_init)
        #: budget_schedule "growth": (window share, count) where the budget was measured, None before
        self.budget_probe: Optional[tuple[float, int]] = None
        #: budget_probe_from "trough": (window share, count) of the fewest Gaussians seen before the probe
        self.budget_trough: tuple[float, int] = (0.0, self._n_init)
        self.crop_rng = torch.Generator().manual_seed(config.seed + 4)
        self._levels: Optional[list[tuple[float, float]]] = None  # (downscale, energy kept), resolution schedule
        self._targets: dict = {}  # (view index, w, h) -> the downsampled image
        #: a cobgs.train.profile.PhaseTimer timing each step's phases, or None (no cost)
        self.timer = None
        #: step() leaves its loss and PSNR on the device until read (StepInfo): no host
        #: synchronisation per iteration on CUDA (train() reads them at its log interval)
        self.lazy_stats = self.device.type == "cuda"
        if config.rasterizer == "gsplat":
            from cobgs.train.gsplat_backend import check_gsplat

            check_gsplat(self.device)

    # -- pieces -----------------------------------------------------------------------------
    def _make_optimizer(self) -> torch.optim.Optimizer:
        c = self.config
        lrs = gaussian_lrs(c, c.position_lr_init, self.extent)
        if c.sparse_adam:
            from cobgs.train.visible_adam import VisibleAdam

            return VisibleAdam.for_model(self.model, lrs, eps=c.adam_eps)
        return self.model.make_adam(lrs, eps=c.adam_eps)

    # -- the fast recipe's schedules ----------------------------------------------------------
    def downscale(self, iteration: Optional[int] = None) -> float:
        """The image downscale of an iteration under the resolution schedule (1: full size).

        The share of the training images' spectral energy that a render at 1/d keeps
        (:func:`spectral_energy_kept`) grows linearly with the iteration, from the share at
        ``resolution_max_downscale`` to all of it at ``resolution_full_at`` x ``iterations``;
        d is the largest level (steps of 0.25) that keeps at least that share.
        """
        c = self.config
        if not c.resolution_schedule:
            return 1.0
        it = self.iteration if iteration is None else iteration
        end = max(1.0, c.resolution_full_at * c.iterations)
        if it >= end:
            return 1.0
        if self._levels is None:
            self._levels = resolution_levels([v.image for v in self.scene.train], c.resolution_max_downscale)
        lo = self._levels[0][1]
        want = lo + (1.0 - lo) * (it / end)
        for d, kept in self._levels:  # largest downscale first
            if kept >= want:
                return d
        return 1.0

    def _target(self, index: int, view: View, width: int, height: int) -> Tensor:
        """The view's image at ``width`` x ``height`` (area-averaged; cached per size)."""
        if (width, height) == (view.camera.width, view.camera.height):
            return view.image
        key = (index, width, height)
        t = self._targets.get(key)
        if t is None:
            img = view.image.permute(2, 0, 1)[None]
            t = torch.nn.functional.interpolate(img, size=(height, width), mode="area")[0].permute(1, 2, 0).contiguous()
            self._targets[key] = t
        return t

    def _crop(self, camera, target: Tensor):
        """A random crop of ``crop_fraction`` of each side of the frame: its camera and image."""
        f = self.config.crop_fraction
        w, h = max(1, int(round(camera.width * f))), max(1, int(round(camera.height * f)))
        x0 = int(torch.randint(0, int(camera.width) - w + 1, (1,), generator=self.crop_rng))
        y0 = int(torch.randint(0, int(camera.height) - h + 1, (1,), generator=self.crop_rng))
        return camera.cropped(x0, y0, w, h), target[y0:y0 + h, x0:x0 + w].contiguous()

    def budget_now(self) -> int:
        """The count the budget allows at this iteration: a line from the initial count to
        the budget at ``budget_full_at`` of the densification window; with ``budget_schedule =
        "resolution"``, the share of full-resolution pixels the iteration renders (1/d^2)."""
        s, c = self.sched, self.config
        start = self._n_init
        if c.budget_schedule == "resolution":
            t = 1.0 / self.downscale() ** 2
        elif c.budget_schedule == "growth" and self.budget_probe is not None:
            t0, start = self.budget_probe
            t = min(1.0, max(0.0, (self.window_share() - t0) / max(1e-9, c.budget_full_at - t0)))
        else:
            span = max(1.0, c.budget_full_at * (s.densify_until - s.densify_from))
            t = min(1.0, max(0.0, (self.iteration - s.densify_from) / span))
        return int(round(start + (self.budget - start) * t)) if self.budget > start else self.budget

    def window_share(self) -> float:
        """How far this iteration is into the densification window, 0 to 1."""
        s = self.sched
        return min(1.0, max(0.0, (self.iteration - s.densify_from) / max(1, s.densify_until - s.densify_from)))

    def _probe_growth(self, n: int) -> None:
        """budget_schedule "growth": once budget_probe_at of the window has passed, the count 3DGS's
        rule grew to, extrapolated linearly over the whole window, becomes the budget.

        With ``budget_probe_from = "trough"`` the line starts at the fewest Gaussians seen so far
        (``budget_trough``) and the probe waits until budget_probe_at of the window has passed
        since then; a count that only falls is never probed (3DGS's rule to the window's end)."""
        c, t = self.config, self.window_share()
        t0, n_low = 0.0, self._n_init
        if c.budget_probe_from == "trough":
            if n < self.budget_trough[1]:
                self.budget_trough = (t, n)
            t0, n_low = self.budget_trough
        if t - t0 < c.budget_probe_at or t <= 0:
            return
        self.budget_probe = (t, n)
        if c.budget_probe_from == "start":  # (written as first measured: the same integers)
            self.budget = max(n, int(round(self._n_init + (n - self._n_init) / t)))
        else:  # the growth since the trough, as a straight line through it and (t, n), at the window's end
            self.budget = max(n, int(round(n + (n - n_low) * (1.0 - t) / (t - t0))))

    def _reset_stats(self) -> None:
        n, dev = len(self.model), self.model.device
        self.grad_accum = torch.zeros(n, device=dev)
        self.grad_count = torch.zeros(n, device=dev)
        self.max_radii = torch.zeros(n, device=dev)

    def _next_view(self) -> tuple[int, View]:
        if not self.view_queue:
            self.view_queue = torch.randperm(len(self.scene.train), generator=self.view_rng).tolist()
        i = self.view_queue.pop()
        return i, self.scene.train[i]

    def _update_lr(self) -> None:
        c = self.config
        lr = expon_lr(self.iteration, c.position_lr_init, c.position_lr_final, self.sched.position_lr_decay)
        for g in self.optimizer.param_groups:
            if g["name"] == "means":
                g["lr"] = lr * self.extent

    # -- one iteration ----------------------------------------------------------------------
    def step(self) -> dict:
        """One optimisation iteration; returns ``{"loss", "psnr", "image"}`` of the view.
        With ``TrainConfig.fast_kernels`` (native backend, CPU), its forward and backward
        passes take the CPU kernels' fast path (:func:`cobgs.render.ops.cpu_fast_path`)."""
        c = self.config
        if not (c.fast_kernels and c.backend == "native" and self.device.type == "cpu"):
            return self._step()
        from cobgs.render.ops import cpu_fast_path

        with cpu_fast_path(True):
            return self._step()

    def _phase(self, name: str):
        """The timer's context for a phase of the step (cobgs.train.profile), or nothing."""
        from cobgs.train.profile import no_phase

        return self.timer.phase(name) if self.timer is not None else no_phase(name)

    def _render(self, camera, bg):
        """The forward pass: ours, or gsplat's ``rasterization`` (TrainConfig.rasterizer)."""
        if self.config.rasterizer == "gsplat":
            from cobgs.train.gsplat_backend import render_gsplat

            return render_gsplat(self.model, camera, bg)
        return render(self.model, camera, bg, backend=self.config.backend)

    def _step(self) -> dict:
        c, s = self.config, self.sched
        self.iteration += 1
        it = self.iteration
        self._update_lr()
        if it % s.sh_degree_interval == 0 and self.model.active_sh_degree < self.model.sh_degree:
            self.model.active_sh_degree += 1
        index, view = self._next_view()
        camera, target = view.camera, view.image
        d = self.downscale(it)
        stats = it < s.densify_until  # the step feeds the densification statistics
        if stats and d != 1.0 and c.densify_stats_every > 0:  # TrainConfig.densify_stats_every
            if it % c.densify_stats_every == 0:
                d = 1.0
            else:
                stats = False
        if d != 1.0:
            camera = camera.scaled(d)
            target = self._target(index, view, int(camera.width), int(camera.height))
        elif c.crop_fraction < 1.0 and it >= s.densify_until:
            camera, target = self._crop(camera, target)
        bg = torch.rand(3, generator=self.bg_rng) if c.random_background else self.background
        with self._phase("render"):
            out = self._render(camera, bg)
            if stats:  # the densification statistics read its gradient
                out.means2d.retain_grad()
            img = out.image
        with self._phase("loss"):
            loss = photometric_loss(img, target, c.ssim_weight)
        with self._phase("backward"):
            loss.backward()

        with torch.no_grad():
            if stats:
                with self._phase("stats"):
                    self._accumulate(out.radii, out.means2d.grad, camera.width, camera.height,
                                     d if c.densify_grad_rescale else 1.0)
            with self._phase("optimizer"):
                if c.sparse_adam:
                    self.optimizer.step(visible=out.radii > 0)
                else:
                    self.optimizer.step()
                self.optimizer.zero_grad(set_to_none=True)
            if it < s.densify_until:
                with self._phase("densify"):
                    if it > s.densify_from and it % s.densify_interval == 0:
                        self.densify_and_prune()
                    if it % s.opacity_reset_interval == 0 or (self.white_background and it == s.densify_from):
                        self.reset_opacity()
            with self._phase("sync"):
                mse = torch.mean((img.detach().clamp(0, 1) - target) ** 2)
                info = StepInfo(loss.detach(), mse, img.detach(), (int(camera.width), int(camera.height)))
                if not self.lazy_stats:
                    info.read()
        if self.timer is not None:
            self.timer.steps += 1
        return info

    def _accumulate(self, radii: Tensor, grad2d: Optional[Tensor], width: int, height: int,
                    factor: float = 1.0) -> None:
        if grad2d is None:
            return
        # Dense masked updates (no boolean indexing: nonzero() is a large share of a CPU
        # iteration at 100k Gaussians). Culled Gaussians have radius 0 and zero gradient.
        vis = (radii > 0).to(self.grad_count.dtype)
        # The 2e-4 threshold is in NDC units: x_pix = ((x_ndc + 1) W - 1) / 2 (times ``factor``:
        # TrainConfig.densify_grad_rescale's d for a render at 1/d).
        scale = torch.tensor([factor * width / 2.0, factor * height / 2.0], dtype=grad2d.dtype, device=grad2d.device)
        self.grad_accum += (grad2d * scale).norm(dim=-1) * vis
        self.grad_count += vis
        torch.maximum(self.max_radii, radii.to(self.max_radii.dtype), out=self.max_radii)

    def densify_and_prune(self) -> dict:
        """Clone / split on the averaged gradient, then prune; resets the statistics.

        Returns:
            counts: ``cloned``, ``split`` (parents), ``pruned``.
        """
        c, m = self.config, self.model
        n0 = len(m)
        grads = self.grad_accum / self.grad_count.clamp_min(1)
        grads[self.grad_count == 0] = 0.0
        big = m.scales.max(dim=1).values > c.dense_scale_fraction * self.extent
        growth = c.budget_schedule == "growth"
        if growth and self.budget_probe is None:
            self._probe_growth(n0)
        if self.budget and not (growth and self.budget_probe is None):
            hot = self._budget_pick(grads, big, n0)
            if c.budget_edge_exempt > 0:  # the strongest edges densify past the ceiling
                hot |= grads >= c.budget_edge_exempt * c.densify_grad_threshold_ndc
        else:
            hot = grads >= c.densify_grad_threshold_ndc
        clone = hot & ~big
        split = hot & big
        if c.max_gaussians > 0:
            budget = c.max_gaussians - n0
            if int(clone.sum()) + int(split.sum()) * (c.split_children - 1) > budget:
                clone = split = torch.zeros_like(hot)
        n_clone, n_split = int(clone.sum()), int(split.sum())
        opts = [self.optimizer]
        # Clones are exact copies (they separate under the next gradient steps); they are
        # appended after the originals, so the split mask is padded with False for them.
        split_padded = torch.cat([split, torch.zeros(n_clone, dtype=torch.bool, device=split.device)])
        if n_clone:
            m.append(m.gather(clone), opts)
        if n_split:
            children = m.split_children(
                split_padded, c.split_children, c.split_scale_divisor, generator=self.split_rng
            )
            m.replace(split_padded, children, opts)
        # Screen-radius statistic, edited like the model: clones copy their original's,
        # split parents leave, children start at 0.
        radii = torch.cat([self.max_radii, self.max_radii[clone]])
        if n_split:
            radii = torch.cat([radii[~split_padded], radii.new_zeros(n_split * c.split_children)])
        prune = m.opacities.detach() < c.prune_min_opacity
        if self.iteration > self.sched.opacity_reset_interval:
            prune |= m.scales.detach().max(dim=1).values > c.prune_max_world_scale_fraction * self.extent
            if c.prune_max_screen_radius_px > 0:
                prune |= radii > c.prune_max_screen_radius_px
        n_prune = int(prune.sum())
        if n_prune:
            m.keep(~prune, opts)
        self._reset_stats()
        return {"cloned": n_clone, "split": n_split, "pruned": n_prune}

    def _budget_pick(self, grads: Tensor, big: Tensor, n0: int) -> Tensor:
        """The Gaussians to densify under the budget: highest averaged gradient first, as many
        as fit below :meth:`budget_now` (a clone adds one, a split ``split_children - 1``);
        never-seen Gaussians (no gradient) are not candidates, nor, under
        ``budget_threshold_gate``, those below 3DGS's gradient threshold."""
        room = self.budget_now() - n0
        pick = torch.zeros_like(big)
        if room <= 0:
            return pick
        candidate = self.grad_count > 0
        if self.config.budget_threshold_gate:
            candidate &= grads >= self.config.densify_grad_threshold_ndc
        order = torch.argsort(torch.where(candidate, grads, grads.new_full((), -1.0)), descending=True)
        order = order[candidate[order]]
        cost = torch.where(big[order], self.config.split_children - 1, 1).to(torch.int64)
        take = order[torch.cumsum(cost, 0) <= room]
        pick[take] = True
        return pick

    def reset_opacity(self) -> None:
        """Clamp every opacity to at most ``opacity_reset_value`` and zero its Adam moments."""
        m = self.model
        cap = inverse_sigmoid(torch.tensor(self.config.opacity_reset_value))
        m.set_tensor("opacity_logits", torch.minimum(m.opacity_logits.detach(), cap), [self.optimizer])

    # -- checkpoints --------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {
            "version": CHECKPOINT_VERSION,
            "config": dataclasses.asdict(self.config),
            "iteration": self.iteration,
            "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "stats": (self.grad_accum.clone(), self.grad_count.clone(), self.max_radii.clone()),
            "view_queue": list(self.view_queue),
            "view_rng": self.view_rng.get_state(),
            "split_rng": self.split_rng.get_state(),
            "bg_rng": self.bg_rng.get_state(),
            "crop_rng": self.crop_rng.get_state(),
            "budget": (self.budget, self.budget_probe),
            "budget_trough": self.budget_trough,
        }

    def load_state_dict(self, state: dict) -> None:
        if state.get("version") != CHECKPOINT_VERSION:
            raise DataError(f"checkpoint version {state.get('version')} != {CHECKPOINT_VERSION}")
        saved = {k: v for k, v in state["config"].items() if k not in ("log_interval_its", "checkpoint_interval_its")}
        now = {k: v for k, v in dataclasses.asdict(self.config).items() if k in saved}
        diff = sorted(k for k in saved if saved[k] != now.get(k) and k != "iterations")
        if diff:
            raise InputError(
                "checkpoint was written with a different TrainConfig: "
                + ", ".join(f"{k}={saved[k]!r} (now {now.get(k)!r})" for k in diff)
            )
        self.model = GaussianModel.from_state_dict(state["model"]).to(self.device)
        self.optimizer = self._make_optimizer()
        self.optimizer.load_state_dict(state["optimizer"])
        self.grad_accum, self.grad_count, self.max_radii = (t.to(self.device).clone()
                                                            for t in state["stats"])
        self.iteration = int(state["iteration"])
        self.view_queue = list(state["view_queue"])
        self.view_rng.set_state(state["view_rng"])
        self.split_rng.set_state(state["split_rng"])
        if "bg_rng" in state:  # absent in checkpoints written before random_background existed
            self.bg_rng.set_state(state["bg_rng"])
        if "crop_rng" in state:  # absent before crop_fraction / budget_schedule "growth"
            self.crop_rng.set_state(state["crop_rng"])
            self.budget, self.budget_probe = state["budget"][0], state["budget"][1]
            if self.budget_probe is not None:
                self.budget_probe = (float(self.budget_probe[0]), int(self.budget_probe[1]))
        if "budget_trough" in state:  # absent before budget_probe_from
            self.budget_trough = (float(state["budget_trough"][0]), int(state["budget_trough"][1]))

    def save_checkpoint(self, path: os.PathLike | str) -> Path:
        """Write the full state atomically (temporary file + rename)."""
        return save_atomic(self.state_dict(), path)

    def load_checkpoint(self, path: os.PathLike | str) -> None:
        path = Path(path)
        if not path.is_file():
            raise DataError("checkpoint not found", path)
        state = _load_safely(path)
        if not isinstance(state, dict) or "model" not in state:
            raise DataError("not a cobgs training checkpoint (no model state)", path)
        self.load_state_dict(state)


def load_model(path: os.PathLike | str) -> GaussianModel:
    """The Gaussians of a training checkpoint (``.pt``) or of a PLY file."""
    path = Path(path)
    if path.suffix.lower() == ".ply":
        from cobgs.gaussians.ply import load_ply

        return load_ply(path)
    if not path.is_file():
        raise DataError("checkpoint not found", path)
    state = _load_safely(path)
    try:
        return GaussianModel.from_state_dict(state["model"])
    except (KeyError, TypeError, IndexError) as e:
        raise DataError(f"not a cobgs training checkpoint (no model state): {e!r}", path) from e


def _load_safely(path: Path):
    """``torch.load(weights_only=True)``: tensors, numbers, strings, lists, tuples and dicts
    only, so a checkpoint from elsewhere cannot run code when it is read (a pickle of any
    other object is refused, naming the file)."""
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
        raise DataError("refused: the checkpoint holds objects other than tensors, numbers, "
                        "strings, lists and dicts (it is read with torch.load(weights_only=True), "
                        f"which never runs code from the file): {str(e).splitlines()[0]}", path) from e
    except Exception as e:  # torch raises several types for corrupt files
        raise DataError(f"unreadable checkpoint: {e}", path) from e


def save_atomic(obj, path: os.PathLike | str) -> Path:
    """``torch.save`` into a temporary file in the same folder, then rename into place."""
    buf = io.BytesIO()  # (torch.save names records after the file: the same bytes via a buffer)
    torch.save(obj, buf)
    return write_bytes_atomic(path, buf.getbuffer())


def evaluate(
    model: GaussianModel,
    views: Sequence[View],
    background: Sequence[float] = (0.0, 0.0, 0.0),
    backend: str = "native",
) -> dict:
    """PSNR / SSIM of renders against held-out views (renders clamped to [0, 1]).

    Returns:
        ``{"psnr": mean dB, "ssim": mean, "per_view": {name: {"psnr", "ssim"}}}``
        (empty dict without views).
    """
    if not views:
        return {}
    per = {}
    bg = torch.as_tensor(background, dtype=torch.float32)
    with torch.no_grad():
        for v in views:
            img = render(model, v.camera, bg, backend=backend).image.clamp(0, 1)
            per[v.name] = {"psnr": psnr_metric(img, v.image), "ssim": ssim_metric(img, v.image)}
    return {
        "psnr": sum(p["psnr"] for p in per.values()) / len(per),
        "ssim": sum(p["ssim"] for p in per.values()) / len(per),
        "per_view": per,
    }


def peak_rss_bytes() -> int:
    """Peak resident set size of this process (Linux reports KiB)."""
    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024


def check_model_finite(model, where: str) -> None:
    """Raise :class:`DivergenceError` when ``model`` has no Gaussian or a non-finite
    parameter (``where`` names the run and iteration)."""
    if len(model) == 0:
        raise DivergenceError(f"{where}: no Gaussian left (check prune_min_opacity and the learning rates)")
    for k in ("means", "log_scales", "quats", "opacity_logits", "sh0", "shN"):
        t = model.data.get(k)
        if t is not None and t.numel() and not bool(torch.isfinite(t.detach()).all()):
            raise DivergenceError(f"{where}: non-finite values in {k} (a learning rate or loss weight too "
                                  "large?); nothing is saved")


def train(
    scene: Scene,
    config: TrainConfig = TrainConfig(),
    *,
    model: Optional[GaussianModel] = None,
    checkpoint_dir: Optional[os.PathLike | str] = None,
    resume: Optional[os.PathLike | str] = None,
    progress: bool = True,
    evaluate_test: bool = True,
    callback: Optional[Callable[[Trainer, dict], None]] = None,
) -> TrainResult:
    """Optimise a 3DGS model on ``scene.train`` and evaluate it on ``scene.test``.

    Args:
        scene: the posed images (see :mod:`cobgs.data`).
        config: the recipe.
        model: start from this model instead of the SfM / random initialisation.
        checkpoint_dir: when given, ``ckpt_<it>.pt`` is written every
            ``checkpoint_interval_its`` and ``ckpt_final.pt`` at the end.
        resume: checkpoint to continue from (its config must match ``config`` except
            ``iterations``); training continues up to ``config.iterations``.
        progress: show a tqdm bar (iteration, loss, training-view PSNR, Gaussian count, and
            under the fast recipe the rendered size and the Gaussian budget).
        evaluate_test: compute held-out PSNR / SSIM at the end.
        callback: called after every iteration with (trainer, step info).

    Returns:
        :class:`TrainResult`.
    """
    trainer = Trainer(scene, config, model)
    if resume is not None:
        trainer.load_checkpoint(resume)
    start = trainer.iteration
    history: list[dict] = []
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=config.iterations, initial=start, desc="train", dynamic_ncols=True)
    t0 = time.perf_counter()
    ema_loss = None
    plateau = _Plateau(config, trainer)
    checked = start  # (lazy statistics: the iteration of the last finite check)
    while trainer.iteration < config.iterations:
        info = trainer.step()
        it = trainer.iteration
        log_now = it % config.log_interval_its == 0 or it == config.iterations
        if trainer.lazy_stats:
            # on the device, read at the log interval: a non-finite loss stays non-finite in the mean
            loss_t = info.loss_tensor.double()
            ema_loss = loss_t if ema_loss is None else 0.9 * ema_loss + 0.1 * loss_t
            if log_now:
                ema_loss = float(ema_loss)
                if not math.isfinite(ema_loss):
                    raise DivergenceError(f"training diverged between iterations {checked + 1} and {it}: a loss "
                                          f"of {ema_loss} ({len(trainer.model)} Gaussians); nothing is saved")
                checked = it
        else:
            if not math.isfinite(info["loss"]):
                raise DivergenceError(f"training diverged at iteration {it}: loss {info['loss']} "
                                      f"({len(trainer.model)} Gaussians); nothing is saved")
            ema_loss = info["loss"] if ema_loss is None else 0.9 * ema_loss + 0.1 * info["loss"]
        if log_now:
            check_model_finite(trainer.model, f"training at iteration {it}")
        if callback is not None:
            callback(trainer, info)
        if it % config.log_interval_its == 0 or it == config.iterations:
            rec = {"it": it, "loss": info["loss"], "psnr": info["psnr"], "num_gaussians": len(trainer.model)}
            history.append(rec)
            if bar is not None:
                extra = {"res": "x".join(map(str, info["resolution"]))} if config.resolution_schedule else {}
                if trainer.budget:
                    extra["budget"] = str(trainer.budget)
                bar.set_postfix(loss=f"{ema_loss:.4f}", psnr=f"{info['psnr']:.2f}", n=str(len(trainer.model)), **extra)
        if bar is not None:
            bar.update(1)
        if checkpoint_dir is not None and config.checkpoint_interval_its > 0 and it % config.checkpoint_interval_its == 0:
            trainer.save_checkpoint(Path(checkpoint_dir) / f"ckpt_{it}.pt")
        if plateau.flat(info.loss_tensor if trainer.lazy_stats else info["loss"]):
            break
    wall = time.perf_counter() - t0
    if bar is not None:
        bar.close()
    if checkpoint_dir is not None:
        trainer.save_checkpoint(Path(checkpoint_dir) / "ckpt_final.pt")
    done = trainer.iteration - start
    ev = evaluate(trainer.model, scene.test, trainer.background.tolist(), config.backend) if evaluate_test else {}
    return TrainResult(
        model=trainer.model,
        iterations=trainer.iteration,
        history=history,
        eval=ev,
        wall_s=wall,
        s_per_it=wall / max(done, 1),
        peak_rss_bytes=peak_rss_bytes(),
        adam_moments=export_moments(trainer.optimizer),
        budget=trainer.budget,
        stopped_at=plateau.stopped_at,
    )


class _Plateau:
    """TrainConfig.stop_at_plateau: whether the training loss has flattened (the mean of the
    last window of ``plateau_window_its`` iterations gains less than the threshold, relative to
    the window before), counted only once densification has ended and the renders are full size."""

    def __init__(self, config: TrainConfig, trainer: "Trainer"):
        self.config, self.trainer = config, trainer
        self.window = 0.0  # the window's sum (a device tensor under lazy statistics: read once per window)
        self.count = 0
        self.previous: Optional[float] = None
        self.stopped_at = 0

    def flat(self, loss) -> bool:
        c, tr = self.config, self.trainer
        if c.stop_at_plateau <= 0 or tr.iteration < tr.sched.densify_until or tr.downscale() != 1.0:
            return False
        self.window = self.window + (loss.double() if isinstance(loss, Tensor) else loss)
        self.count += 1
        if self.count < c.plateau_window_its:
            return False
        mean = float(self.window) / self.count
        self.window, self.count = 0.0, 0
        prev, self.previous = self.previous, mean
        if prev is not None and prev > 0 and (prev - mean) / prev < c.stop_at_plateau:
            self.stopped_at = tr.iteration
            return True
        return False
