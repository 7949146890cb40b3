"""The baseline's Adam moments: exported by training, restored by the COB-GS texture stages.

The released COB-GS starts its refinement from the 3DGS *checkpoint* (model and optimizer
state), not from the PLY: its TEXTURE stages continue the baseline's Adam, with the
baseline's first and second moments and step count. That matters. With fresh (zero)
moments Adam's first bias-corrected steps move every parameter by about its learning rate
in the direction of its gradient sign — opacity logits by 0.025, log-scales by 0.005 per
step, for every Gaussian in view — which disturbs a converged scene; with the baseline's
moments the step of a converged parameter is small, and only Gaussians with large,
consistent gradients (the split children, whose moments start at zero) move quickly.

A standard 3DGS PLY cannot hold these moments, so training exports them
(:attr:`cobgs.train.optimize.TrainResult.adam_moments`) and the pipeline's ``train`` stage writes
them next to ``scene.ply`` as ``adam_moments.pt`` (:func:`save_moments`).

Format (a ``torch.save`` dict)::

    {"format": "cobgs-adam-moments", "version": 1, "num_gaussians": N,
     "tensors": {name: {"exp_avg": [N, ...], "exp_avg_sq": [N, ...], "step": []}}}

with one entry per optimised model tensor (``means``, ``sh0``, ``shN``,
``opacity_logits``, ``log_scales``, ``quats``), each moment shaped like the tensor.
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Mapping, Optional

import torch
from torch import Tensor

from cobgs._atomic import write_bytes_atomic
from cobgs.configs import Files
from cobgs.errors import DataError, InputError

__all__ = ["MOMENTS_FILE", "export_moments", "load_moments", "save_moments", "read_moments"]

MOMENTS_FORMAT = "cobgs-adam-moments"
MOMENTS_VERSION = 1
MOMENTS_FILE = Files.MOMENTS  # the name the pipeline's train stage writes (the artifact catalog)
_KEYS = ("exp_avg", "exp_avg_sq", "step")

Moments = Mapping[str, Mapping[str, Tensor]]


def export_moments(optimizer: torch.optim.Optimizer) -> dict[str, dict[str, Tensor]]:
    """The Adam state of every named parameter group: ``{name: {exp_avg, exp_avg_sq, step}}``.

    Groups need a ``"name"`` key (:meth:`cobgs.gaussians.model.GaussianModel.make_adam` sets it)
    and one parameter each. Parameters without state (never stepped) are left out. The
    tensors are detached references, not copies (:func:`load_moments` copies).
    """
    out: dict[str, dict[str, Tensor]] = {}
    for g in optimizer.param_groups:
        name = g.get("name")
        if name is None or len(g["params"]) != 1:
            raise InputError("export_moments needs named parameter groups of one tensor each "
                             "(GaussianModel.make_adam)")
        st = optimizer.state.get(g["params"][0])
        if not st:
            continue
        out[name] = {k: torch.as_tensor(st[k]).detach() for k in _KEYS}
    return out


def load_moments(optimizer: torch.optim.Optimizer, moments: Moments, source: str = "moments") -> list[str]:
    """Seed ``optimizer``'s state with ``moments`` (copies), group by group name.

    An entry's moments must have its parameter's shape; entries for other tensors are
    ignored. A named group without an entry starts from zero moments, as Adam starts any
    tensor: training leaves out the tensors it never stepped (``shN`` below the first
    SH-degree step, 1000 iterations), and their first step is then Adam's first.

    Args:
        optimizer: an Adam whose groups carry a ``"name"`` (``make_adam``).
        moments: ``{name: {exp_avg, exp_avg_sq, step}}`` (:func:`export_moments`,
            :func:`read_moments`).
        source: what the moments are, for error messages (e.g. a file path).

    Returns:
        the names of the groups seeded.

    Raises:
        InputError: an entry's shape, dtype or keys do not match its group.
    """
    names = []
    for g in optimizer.param_groups:
        name = g.get("name")
        if name is None:
            continue
        p = g["params"][0]
        if name not in moments:
            optimizer.state.pop(p, None)  # zero moments, step 0: Adam's own start
            continue
        entry = moments[name]
        missing = [k for k in _KEYS if k not in entry]
        if missing:
            raise InputError(f"{source}: moments of {name!r} lack {missing}")
        for k in ("exp_avg", "exp_avg_sq"):
            t = entry[k]
            if tuple(t.shape) != tuple(p.shape):
                raise InputError(f"{source}: {name}.{k} has shape {list(t.shape)}, the model's {name!r} has "
                                 f"{list(p.shape)} (moments saved with another scene, or the model was edited "
                                 "after training?)")
            if not t.is_floating_point():
                raise InputError(f"{source}: {name}.{k} must be floating point, got {t.dtype}")
        step = torch.as_tensor(entry["step"])
        if step.numel() != 1 or not bool(torch.isfinite(step.float()).all()) or float(step) < 0:
            raise InputError(f"{source}: {name}.step must be one finite count >= 0, got {step.tolist()}")
        optimizer.state[p] = {
            "step": step.reshape(()).to(dtype=torch.float32, device=p.device).clone(),
            "exp_avg": entry["exp_avg"].detach().to(dtype=p.dtype, device=p.device).clone(),
            "exp_avg_sq": entry["exp_avg_sq"].detach().to(dtype=p.dtype, device=p.device).clone(),
        }
        names.append(name)
    return names


def save_moments(path: os.PathLike | str, moments: Moments, num_gaussians: int) -> Path:
    """Write ``moments`` to ``path`` (complete or absent: temporary file, then rename)."""
    path = Path(path)
    for name, entry in moments.items():
        for k in ("exp_avg", "exp_avg_sq"):
            if entry[k].shape[0] != num_gaussians:
                raise InputError(f"moments of {name!r}: {k} has {entry[k].shape[0]} rows, expected {num_gaussians}")
    payload = {"format": MOMENTS_FORMAT, "version": MOMENTS_VERSION, "num_gaussians": int(num_gaussians),
               "tensors": {n: {k: torch.as_tensor(e[k]).detach().cpu() for k in _KEYS} for n, e in moments.items()}}
    # Through a buffer: torch.save names the archive's records after the file it writes,
    # and the temporary name is random, so saving to it directly made every file
    # different; from a buffer the same moments are the same bytes.
    buf = io.BytesIO()
    torch.save(payload, buf)
    return write_bytes_atomic(path, buf.getbuffer())


def read_moments(path: os.PathLike | str, num_gaussians: Optional[int] = None,
                 device: torch.device | str = "cpu") -> dict[str, dict[str, Tensor]]:
    """Read a moments file written by :func:`save_moments`.

    Args:
        path: the file.
        num_gaussians: the scene's size; the file must match it (None: not checked).
        device: where to put the tensors.

    Raises:
        DataError: missing, unreadable, of another format or version, malformed, or for
            a scene of another size.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError("Adam moments file not found", path)
    try:
        d = torch.load(path, map_location=device, weights_only=True)
    except Exception as e:  # torch raises several types for corrupt / foreign files
        raise DataError(f"unreadable Adam moments file: {e}", path) from e
    if not isinstance(d, dict) or d.get("format") != MOMENTS_FORMAT:
        raise DataError(f"not a {MOMENTS_FORMAT} file (field 'format' is "
                        f"{d.get('format') if isinstance(d, dict) else type(d).__name__!r})", path)
    if d.get("version") != MOMENTS_VERSION:
        raise DataError(f"field 'version' is {d.get('version')!r}, expected {MOMENTS_VERSION}", path)
    n = d.get("num_gaussians")
    tensors = d.get("tensors")
    if not isinstance(n, int) or not isinstance(tensors, dict):
        raise DataError("fields 'num_gaussians' (int) and 'tensors' (dict) are required", path)
    if num_gaussians is not None and n != num_gaussians:
        raise DataError(f"field 'num_gaussians' is {n}, the scene has {num_gaussians} Gaussians "
                        "(moments of another training run?)", path)
    for name, entry in tensors.items():
        if not isinstance(entry, dict) or any(k not in entry for k in _KEYS):
            raise DataError(f"tensors[{name!r}] must hold {list(_KEYS)}", path)
        for k in ("exp_avg", "exp_avg_sq"):
            t = entry[k]
            if not isinstance(t, Tensor) or t.dim() < 1 or t.shape[0] != n:
                raise DataError(f"tensors[{name!r}][{k!r}] must be a tensor with {n} rows, got "
                                f"{list(t.shape) if isinstance(t, Tensor) else type(t).__name__}", path)
    return tensors
