"""What every segmentation method returns (COB-GS, its ablations and the peers alike).

One result type makes the comparison side by side: the evaluation (:mod:`cobgs.refine.segment`)
only needs the scene after the method (``model``), which Gaussians are the object
(``foreground``), which remain when the object is removed (``background``) and the value
each foreground Gaussian contributes to the rendered object mask (``mask_values``).
"""

from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass, field
from typing import Optional

import torch
from torch import Tensor

from cobgs.memory import release_free_memory
from cobgs.errors import InputError
from cobgs.gaussians.model import GaussianModel


@dataclass
class StageStats:
    """One stage of a refinement (or one pass of a peer).

    Attributes:
        kind: "mask", "texture", "label_pass" (multi-object final pass), or a peer's pass
            name ("sa3d_pass", "flashsplat_vote").
        index: position among all stages, from 0.
        iterations: iterations (views rendered) in the stage.
        gaussians_start, gaussians_end: model size before / after the stage (after its
            split or pruning).
        ambiguous: Gaussians with stage-mean score < δ at the end of a mask stage (−1
            where not applicable).
        ambiguous_large: of those, the ones above the split size (−1 where n/a).
        split: parents split at the end of the stage.
        pruned: Gaussians removed from the scene at the end of the stage.
        dropped: Gaussians taken out of the optimised set but kept in the scene
            (SA3D-GS's label <= 0 after its first pass); not ``pruned``.
        skipped_views: views of the stage left out by the method's own rule
            (SA3D-GS: render-vs-mask IoU below its bar).
        mean_loss: mean loss over the stage's iterations (nan where there is none).
        wall_s: wall time of the stage.
    """

    kind: str
    index: int
    iterations: int
    gaussians_start: int
    gaussians_end: int
    ambiguous: int = -1
    ambiguous_large: int = -1
    split: int = 0
    pruned: int = 0
    dropped: int = 0
    skipped_views: int = 0
    mean_loss: float = float("nan")
    wall_s: float = 0.0

    def as_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class RefineResult:
    """The outcome of one method on one object of one scene.

    Attributes:
        method: a name of :data:`cobgs.refine.methods.REGISTRY` ("cobgs", "nosplit", "sa3d", "flashsplat",
            "ngs"), or a caller's label.
        object_name: the object segmented.
        model: the scene after the method (refined for COB-GS; the input scene, with a
            score extra, for label-only methods).
        foreground: [N] bool, the object's Gaussians.
        background: [N] bool, the Gaussians kept when the object is removed.
        mask_values: [N] float32, each Gaussian's value in the rendered object mask
            (COB-GS: its label; hard-assignment peers: 1).
        stages: per-stage statistics.
        stage_scores: [N_s] float32 stage-mean score of every mask stage (before that
            stage's split), for the δ sweep (paper Fig. 7); empty when not recorded.
        ambiguous_final: ambiguous Gaussians (score < δ) at the end, before RAEM (−1 n/a).
        num_gaussians_start, num_gaussians_end: scene size before / after.
        wall_s: total wall time.
        peak_mem_bytes: peak resident memory above the level at the start (sampled).
        config: the method's parameters as a plain dict.
        texture_moments: the COB-GS texture Adam's final moments (only when asked for:
            :func:`cobgs.refine.alternation.refine` ``return_moments``), else None.
        mask_threshold: the bar of this method's object render (None: the caller's,
            0.5 in docs/method.md §2; SA3D-GS's official render: 0.1 on composited raw labels).
        raem_keep: [N before RAEM] bool, the Gaussians RAEM kept (None: RAEM removed
            nothing or did not run).
        raem_removed: the Gaussians RAEM removed, as a model (None as above); with
            ``raem_keep`` they give back the scene before the final pruning
            (:meth:`model_before_raem`: paper Table 4 measures texture there).
        foreground_in_scene: [N] bool, the object's Gaussians where it is rendered within the
            scene (occluders in front), when that differs from ``foreground``: the labels'
            verdict of ``RefineConfig.object_check = "per_use"``. None: ``foreground`` serves
            both uses.
        mask_render: how the method's own evaluation renders the object's mask: "object" (the
            foreground alone, ``mask_values`` blended, above the bar), or LUDVIG's
            "scene_minmax" / "scene_minmax_li" (every Gaussian with its ``mask_values`` on a
            black background, the render min-max normalised, above the bar / Li's threshold;
            :mod:`cobgs.refine.ludvig`).
    """

    method: str
    object_name: str
    model: GaussianModel
    foreground: Tensor
    background: Tensor
    mask_values: Tensor
    stages: list[StageStats] = field(default_factory=list)
    stage_scores: list[Tensor] = field(default_factory=list)
    ambiguous_final: int = -1
    num_gaussians_start: int = 0
    num_gaussians_end: int = 0
    wall_s: float = 0.0
    peak_mem_bytes: int = 0
    config: dict = field(default_factory=dict)
    texture_moments: Optional[dict] = None
    mask_threshold: Optional[float] = None
    raem_keep: Optional[Tensor] = None
    raem_removed: Optional[GaussianModel] = None
    foreground_in_scene: Optional[Tensor] = None
    mask_render: str = "object"

    def model_before_raem(self) -> GaussianModel:
        """The scene before RAEM's pruning (``model`` itself when nothing was pruned)."""
        if self.raem_keep is None or self.raem_removed is None:
            return self.model
        return restore_pruned(self.model, self.raem_keep, self.raem_removed)

    def summary(self) -> dict:
        """JSON-ready numbers (no tensors) for manifests and reports."""
        return {
            "method": self.method,
            "object": self.object_name,
            "num_gaussians_start": self.num_gaussians_start,
            "num_gaussians_end": self.num_gaussians_end,
            "foreground": int(self.foreground.sum()),
            "background": int(self.background.sum()),
            "ambiguous_final": self.ambiguous_final,
            "splits": sum(s.split for s in self.stages),
            "pruned": sum(s.pruned for s in self.stages),
            "wall_s": self.wall_s,
            "peak_mem_bytes": self.peak_mem_bytes,
            "dropped": sum(s.dropped for s in self.stages),
            "skipped_views": sum(s.skipped_views for s in self.stages),
            "raem_pruned": 0 if self.raem_keep is None else int((~self.raem_keep).sum()),
            "mask_threshold": self.mask_threshold,
            "stages": [s.as_dict() for s in self.stages],
            "config": dict(self.config),
            # (only where it is not the object render: earlier refine.json files stay the same bytes)
            **({"mask_render": self.mask_render} if self.mask_render != "object" else {}),
        }


def restore_pruned(kept: GaussianModel, keep: Tensor, removed: GaussianModel) -> GaussianModel:
    """The model before a pruning ``keep`` ([N] bool) that left ``kept`` and removed
    ``removed``: every Gaussian back at its old index, extras included."""
    keep = keep.to(torch.bool)
    if int(keep.sum()) != len(kept) or int((~keep).sum()) != len(removed):
        raise InputError(f"cannot restore a pruning: the mask keeps {int(keep.sum())} of {keep.numel()} "
                         f"Gaussians, the models hold {len(kept)} kept and {len(removed)} removed")
    if set(kept.data) != set(removed.data):
        raise InputError(f"kept and removed Gaussians differ in their tensors: {sorted(kept.data)} vs "
                         f"{sorted(removed.data)}")
    keep = keep.to(kept.device)
    rows = {}
    for k, a in kept.data.items():
        b = removed.data[k].to(a.device)
        out = torch.empty((keep.numel(),) + tuple(a.shape[1:]), dtype=a.dtype, device=a.device)
        out[keep] = a.detach()
        out[~keep] = b.detach()
        rows[k] = out
    return GaussianModel.from_state_dict({"tensors": rows, "fill": dict(kept.fill),
                                          "active_sh_degree": kept.active_sh_degree})


def current_rss_bytes() -> int:
    """Resident set size of this process now (Linux /proc; 0 where unavailable)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return 0


class PeakMemory:
    """Samples the process RSS in a thread; ``peak_bytes`` is the peak above the start.

    The process-wide ``ru_maxrss`` cannot attribute memory to one method when several
    run in one process (it only grows), hence the sampling; free allocator pages are
    returned to the OS first (:func:`release_free_memory`) so that the increase is the
    method's. Use as a context manager.

    Args:
        interval_s: sampling period.
    """

    def __init__(self, interval_s: float = 0.005):
        self.interval_s = interval_s
        self.start = 0
        self.peak = 0
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None

    def __enter__(self) -> "PeakMemory":
        release_free_memory()
        self.start = self.peak = current_rss_bytes()
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, current_rss_bytes())
            time.sleep(self.interval_s)

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self.peak = max(self.peak, current_rss_bytes())

    @property
    def peak_bytes(self) -> int:
        return max(0, self.peak - self.start)
