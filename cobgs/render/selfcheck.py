"""Checks a user can run on their own machine (``cobgs doctor``): does the native rasterizer
render what the pure-PyTorch reference renders, and how fast is it.

* :func:`parity`: a seeded 200-Gaussian scene (no extreme values) rendered in float32 by the
  native ops on a device and in float64 by :mod:`cobgs.render.reference` on the CPU, with
  gradients of a fixed random loss. Tolerances are the test suite's float32 ones
  (tests/render/test_rasterize.py ``test_float32_matches_float64_reference``): image and alpha
  within 1e-4 absolute (colours are sums of ~20 float32 terms of size <= 1); every gradient
  within 1e-3 of its tensor's largest entry (float32 sums over ~50 pairs per Gaussian with
  cancellations); projected radii equal.
* :func:`timing`: forward + backward of one random 100k-Gaussian float32 render at 504x378
  (the benchmark bar of tests/benchmarks), median of a few repetitions after a warm-up.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field
from typing import Optional

import torch

#: The tolerances of :func:`parity` (see the module docstring).
IMAGE_ATOL = 1e-4
GRAD_RTOL_OF_MAX = 1e-3
_DIFF = ("means", "quats", "scales", "opacities", "features", "background")


def random_scene(n: int, width: int, height: int, seed: int = 0, channels: int = 3,
                 dtype: torch.dtype = torch.float64) -> dict:
    """``n`` Gaussians in front of a slightly rotated pinhole camera (depth 1..5, sizes
    0.3..6 px, opacities in (0, 1)), as keyword arguments of :func:`cobgs.rasterize`."""
    g = torch.Generator().manual_seed(seed)

    def rnd(*shape):
        return torch.rand(*shape, generator=g, dtype=dtype)

    f = 0.9 * max(width, height)
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]], dtype=dtype)
    a = 0.2
    R = torch.tensor([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]],
                     dtype=dtype)
    t = torch.tensor([0.1, -0.2, 0.5], dtype=dtype)
    viewmat = torch.eye(4, dtype=dtype)
    viewmat[:3, :3], viewmat[:3, 3] = R, t
    z = 1 + 4 * rnd(n)
    x = (2 * rnd(n) - 1) * 1.2 * (width / 2 / f) * z
    y = (2 * rnd(n) - 1) * 1.2 * (height / 2 / f) * z
    scales = torch.exp(math.log(0.3) + math.log(20.0) * rnd(n, 3)) * z[:, None] / f
    means = (torch.stack([x, y, z], -1) - t) @ R
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    return dict(means=means, quats=quats, scales=scales, opacities=0.05 + 0.9 * rnd(n), features=rnd(n, channels),
                viewmat=viewmat, K=K, width=width, height=height, background=rnd(channels))


def _to(scene: dict, device: str, dtype: torch.dtype) -> dict:
    return {k: (v.to(device=device, dtype=dtype) if torch.is_tensor(v) else v) for k, v in scene.items()}


def _render(scene: dict, backend: str, seed: int = 123):
    import cobgs

    leaves = {k: (v.clone().requires_grad_(True) if k in _DIFF else v) for k, v in scene.items()}
    out = cobgs.rasterize(**leaves, backend=backend)
    g = torch.Generator().manual_seed(seed)
    gi = torch.randn(out.image.shape, generator=g, dtype=torch.float64).to(out.image)
    ga = torch.randn(out.alpha.shape, generator=g, dtype=torch.float64).to(out.alpha)
    ((out.image * gi).sum() + (out.alpha * ga).sum()).backward()
    return out, {k: leaves[k].grad for k in _DIFF}


@dataclass
class ParityResult:
    device: str
    ok: bool
    image_max_abs: float = math.nan
    alpha_max_abs: float = math.nan
    grad_max_rel: dict = field(default_factory=dict)  # per tensor: max |diff| / max |reference|
    radii_equal: bool = False
    error: str = ""

    def to_json(self) -> dict:
        return asdict(self)


def parity(device: str = "cpu", n: int = 200, width: int = 48, height: int = 32) -> ParityResult:
    """Native float32 on ``device`` against the float64 reference (module docstring)."""
    scene = random_scene(n, width, height, seed=11)
    try:
        nat, g_nat = _render(_to(scene, device, torch.float32), "native")
        ref, g_ref = _render(scene, "reference")
    except Exception as exc:  # noqa: BLE001 - a broken build or device: reported, not raised
        return ParityResult(device, False, error=f"{type(exc).__name__}: {exc}")
    res = ParityResult(device, True)
    res.image_max_abs = float((nat.image.detach().double().cpu() - ref.image.detach()).abs().max())
    res.alpha_max_abs = float((nat.alpha.detach().double().cpu() - ref.alpha.detach()).abs().max())
    res.radii_equal = bool(torch.equal(nat.radii.cpu(), ref.radii))
    for k in _DIFF:
        scale = max(float(g_ref[k].abs().max()), 1e-30)
        res.grad_max_rel[k] = float((g_nat[k].double().cpu() - g_ref[k]).abs().max()) / scale
    res.ok = (res.image_max_abs <= IMAGE_ATOL and res.alpha_max_abs <= IMAGE_ATOL and res.radii_equal
              and all(v <= GRAD_RTOL_OF_MAX for v in res.grad_max_rel.values()))
    return res


@dataclass
class TimingResult:
    device: str
    n: int
    width: int
    height: int
    fwd_bwd_ms: float = math.nan  # median
    fwd_bwd_ms_min: float = math.nan
    reps: int = 0
    threads: Optional[int] = None
    error: str = ""

    def to_json(self) -> dict:
        return asdict(self)


def timing(device: str = "cpu", n: int = 100_000, width: int = 504, height: int = 378, reps: int = 3) -> TimingResult:
    """Forward + backward of one random ``n``-Gaussian float32 render (median of ``reps``)."""
    res = TimingResult(device, n, width, height, threads=torch.get_num_threads() if device == "cpu" else None)
    try:
        scene = _to(random_scene(n, width, height, seed=5, dtype=torch.float32), device, torch.float32)
        times = []
        for i in range(reps + 1):
            if device.startswith("cuda"):
                torch.cuda.synchronize()
            t0 = time.perf_counter()
            _render(scene, "native")
            if device.startswith("cuda"):
                torch.cuda.synchronize()
            if i:  # the first is a warm-up
                times.append(1e3 * (time.perf_counter() - t0))
    except Exception as exc:  # noqa: BLE001
        res.error = f"{type(exc).__name__}: {exc}"
        return res
    times.sort()
    res.fwd_bwd_ms, res.fwd_bwd_ms_min, res.reps = times[len(times) // 2], times[0], len(times)
    return res


__all__ = ["GRAD_RTOL_OF_MAX", "IMAGE_ATOL", "ParityResult", "TimingResult", "parity", "random_scene", "timing"]
