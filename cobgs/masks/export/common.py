"""Export machinery shared by the SAM2 and Grounding DINO exporters.

* :func:`require` imports a model package lazily with a clear message when it is missing;
* :func:`export_graph` runs ``torch.onnx.export`` at opset 17 and moves the weights to an
  external ``.onnx.data`` file when the graph would pass protobuf's 2 GB limit;
* :func:`verify_graph` runs the written graph with onnxruntime and compares every output
  with the PyTorch module's on the same inputs.
"""

from __future__ import annotations

import importlib
import logging
import os
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import List, Mapping, Optional, Sequence

import numpy as np

from cobgs.errors import CobgsError

log = logging.getLogger("cobgs.masks.export")
OPSET = 17
PROTOBUF_LIMIT = 2 * 1024**3


class ExportError(CobgsError):
    """The export could not be produced or does not match the PyTorch model."""


def require(module: str, what: str, hint: str):
    """Import ``module`` or raise :class:`ExportError` saying what to install."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise ExportError(
            f"exporting {what} needs the Python package '{module}', which cannot be "
            f"imported here ({exc}). {hint}"
        ) from exc


def export_graph(
    module,
    args: Sequence,
    path: Path,
    input_names: Sequence[str],
    output_names: Sequence[str],
    dynamic_axes: Optional[Mapping[str, Mapping[int, str]]] = None,
) -> Path:
    """Export ``module(*args)`` to ``path`` (opset 17, fp32), atomically.

    The TorchScript-based exporter is used: it needs no extra package and handles the
    dynamic axes the contract declares (points, memories, pointers, caption length).
    """
    import onnx
    import torch

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # a private folder: a large export may scatter per-tensor side files next to its graph
    with tempfile.TemporaryDirectory(prefix=".export-", dir=path.parent) as tmpdir:
        tmp = Path(tmpdir) / path.name
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with torch.no_grad():
                torch.onnx.export(
                    module.eval(), tuple(args), str(tmp), dynamo=False, opset_version=OPSET,
                    input_names=list(input_names), output_names=list(output_names),
                    dynamic_axes=dict(dynamic_axes or {}), do_constant_folding=True,
                )
        model = onnx.load(str(tmp), load_external_data=True)
        weights = sum(_tensor_bytes(t) for t in model.graph.initializer)
        data = path.with_name(path.name + ".data")
        out = Path(tmpdir) / "final"
        out.mkdir()
        if weights > PROTOBUF_LIMIT - (64 << 20):
            onnx.save_model(model, str(out / path.name), save_as_external_data=True,
                            all_tensors_to_one_file=True, location=data.name,
                            size_threshold=1024)
        else:
            onnx.save_model(model, str(out / path.name))
        for stale in (path, data):
            if stale.exists():
                stale.unlink()
        if (out / data.name).exists():
            os.replace(out / data.name, data)
        os.replace(out / path.name, path)  # the graph last: it is what readers look for
    log.info("wrote %s (%.1f MB of weights%s)", path, weights / 1e6,
             ", external data" if data.exists() else "")
    return path


def _tensor_bytes(t) -> int:
    import onnx

    n = int(np.prod(t.dims)) if len(t.dims) else 1
    return n * onnx.helper.tensor_dtype_to_np_dtype(t.data_type).itemsize


@dataclass(frozen=True)
class Parity:
    """Largest absolute and relative difference of one output, onnxruntime vs torch."""

    name: str
    max_abs: float  # over the compared elements (rows within tolerance, if rows_axis)
    max_rel: float
    ok: bool
    bad_rows: int = 0  # slices beyond tolerance (only with rows_axis)


def verify_graph(
    path: Path,
    module,
    inputs: Mapping[str, np.ndarray],
    output_names: Sequence[str],
    atol: float = 1e-3,
    rtol: float = 1e-3,
    rows_axis: Optional[int] = None,
    max_bad_rows: float = 0.0,
) -> List[Parity]:
    """Run the graph with onnxruntime and ``module`` with torch on the same inputs.

    Args:
        inputs: our input names -> arrays, in the module's argument order.
        rows_axis, max_bad_rows: tolerate up to this fraction of slices along
            ``rows_axis`` exceeding the tolerance (Grounding DINO: a top-k query selection
            may swap near-tied proposals between runtimes; every other query must match).

    Raises:
        ExportError: an output differs beyond ``atol + rtol * |torch|``.
    """
    import onnxruntime as ort
    import torch

    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got = dict(zip(output_names, sess.run(list(output_names), dict(inputs))))
    with torch.no_grad():
        ref = module.eval()(*[torch.from_numpy(np.asarray(v)) for v in inputs.values()])
    if torch.is_tensor(ref):
        ref = (ref,)
    report = []
    for name, r in zip(output_names, ref):
        r = r.detach().float().cpu().numpy()
        g = got[name].astype(np.float32)
        if r.shape != g.shape:
            raise ExportError(f"{path.name}: output '{name}' has shape {list(g.shape)} in "
                              f"onnxruntime but {list(r.shape)} in torch")
        finite = np.isfinite(r)
        with np.errstate(invalid="ignore"):  # -inf - -inf where the text is padded
            diff = np.abs(g - r)
        max_abs = float(diff[finite].max(initial=0.0))
        max_rel = float((diff[finite] / (np.abs(r[finite]) + 1e-6)).max(initial=0.0))
        off = ~(np.where(finite, diff, 0.0) <= atol + rtol * np.abs(np.where(finite, r, 0.0)))
        off |= np.isfinite(g) != finite
        n_bad = 0
        if rows_axis is not None and r.ndim > rows_axis:
            other = tuple(a for a in range(r.ndim) if a != rows_axis)
            rows = off.any(axis=other)
            n_bad = int(rows.sum())
            ok = n_bad <= max_bad_rows * rows.size
            good = np.expand_dims(~rows, other) if other else ~rows
            good = np.broadcast_to(good, r.shape)
            sel = good & finite
            max_abs = float(diff[sel].max(initial=0.0))
            max_rel = float((diff[sel] / (np.abs(r[sel]) + 1e-6)).max(initial=0.0))
        else:
            ok = not bool(off.any())
        report.append(Parity(name, max_abs, max_rel, ok, n_bad))
    bad = [p for p in report if not p.ok]
    for p in report:
        log.info("%s %s: max |ort - torch| = %.3g (rel %.3g)%s", path.name, p.name, p.max_abs,
                 p.max_rel, f", {p.bad_rows} rows beyond tolerance" if p.bad_rows else "")
    if bad:
        detail = "; ".join(f"'{p.name}' max abs diff {p.max_abs:.3g}"
                           + (f", {p.bad_rows} rows beyond tolerance" if p.bad_rows else "")
                           for p in bad)
        raise ExportError(f"{path.name}: onnxruntime disagrees with PyTorch beyond "
                          f"atol={atol}, rtol={rtol}: {detail}")
    return report


def remove_partial(paths: Sequence[os.PathLike]) -> None:
    for p in paths:
        p = Path(p)
        for f in (p, p.with_name(p.name + ".data")):
            if f.exists():
                f.unlink()
