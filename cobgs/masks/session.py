"""onnxruntime sessions checked against the contract at load time.

A :class:`GraphSession` opens one ONNX file, compares every declared tensor with what the
graph says (name, dtype, rank, fixed sizes) and raises :class:`~cobgs.errors.ModelError`
naming the file, the tensor, what was expected and what was found. At run time it maps
our names onto the export's names (so output order never matters) and counts calls.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Dict, List, Mapping, Optional, Sequence

import numpy as np

from cobgs.errors import ModelError

from cobgs.masks.manifest import GraphSpec, TensorSpec

log = logging.getLogger("cobgs.masks")

# onnxruntime's type strings for the dtypes the contract uses
_ORT_TYPES = {
    "tensor(float)": "float32",
    "tensor(float16)": "float16",
    "tensor(double)": "float64",
    "tensor(int64)": "int64",
    "tensor(int32)": "int32",
    "tensor(bool)": "bool",
    "tensor(uint8)": "uint8",
}


def choose_providers(requested: Optional[Sequence[str]] = None) -> List[str]:
    """Execution providers to ask for: ``requested`` if given, else CUDA when present, CPU.

    Requested providers this onnxruntime build lacks are dropped with a warning (a CPU
    build serves ``["CUDAExecutionProvider", "CPUExecutionProvider"]`` on CPU).

    Raises:
        ModelError: none of the requested providers is in this onnxruntime build.
    """
    import onnxruntime as ort

    available = ort.get_available_providers()
    if requested:
        missing = [p for p in requested if p not in available]
        kept = [p for p in requested if p in available]
        if not kept:
            raise ModelError(
                f"execution provider(s) {missing} not available in this onnxruntime build; "
                f"available: {available}"
            )
        if missing:
            log.warning("onnxruntime build lacks %s (available: %s); using %s", missing,
                        available, kept)
        return kept
    chosen = [p for p in ("CUDAExecutionProvider",) if p in available]
    return chosen + ["CPUExecutionProvider"]


@dataclass
class SessionOptions:
    """How sessions are created.

    Attributes:
        providers: execution providers, best first; None picks CUDA when available, then CPU.
        intra_op_threads: threads per graph; 0 lets onnxruntime decide.
        trace_shapes: record the input shapes of every call (tests and benchmarks).
        spin_wait: let onnxruntime's worker threads busy-wait between runs (lower latency
            when cores are idle; steals them from the host work otherwise).
    """

    providers: Optional[Sequence[str]] = None
    intra_op_threads: int = 0
    trace_shapes: bool = False
    spin_wait: bool = False


@dataclass
class CallStats:
    calls: int = 0
    seconds: float = 0.0
    thread_cpu_seconds: float = 0.0  # CPU time of the calling thread inside the runs
    shapes: List[Dict[str, tuple]] = field(default_factory=list)


def _dims(shape) -> List[object]:
    return [d if isinstance(d, int) else None for d in shape]


class GraphSession:
    """One checked ONNX graph.

    Args:
        spec: the declared tensors (our names, their names, dtypes, shapes).
        options: providers, threads, tracing.
    """

    def __init__(self, spec: GraphSpec, options: Optional[SessionOptions] = None):
        import onnxruntime as ort

        self.spec = spec
        self.options = options or SessionOptions()
        self.stats = CallStats()
        path = spec.path
        if not path.is_file():
            raise ModelError(f"{spec.key}: ONNX file not found", path)
        providers = choose_providers(self.options.providers)
        so = ort.SessionOptions()
        so.log_severity_level = 3
        if not self.options.spin_wait:
            # onnxruntime's workers otherwise busy-wait after each run, taking the cores
            # from the host work between graph calls (10x slower on a 2-core machine)
            so.add_session_config_entry("session.intra_op.allow_spinning", "0")
            so.add_session_config_entry("session.inter_op.allow_spinning", "0")
        if self.options.intra_op_threads:
            so.intra_op_num_threads = int(self.options.intra_op_threads)
        try:
            self.session = ort.InferenceSession(str(path), sess_options=so, providers=providers)
        except Exception as exc:  # onnxruntime raises its own exception types
            raise ModelError(f"{spec.key}: onnxruntime cannot load the graph: {exc}", path) from exc
        actual = self.session.get_providers()
        log.info("%s: requested providers %s, session runs on %s", path.name, providers, actual)
        if providers[0] != "CPUExecutionProvider" and providers[0] not in actual:
            # onnxruntime-gpu quietly falls back to CPU when CUDA/cuDNN do not match
            log.warning(
                "%s: asked for %s but onnxruntime fell back to %s (check the CUDA/cuDNN "
                "versions onnxruntime-gpu was built for)", path.name, providers[0], actual
            )
        self.providers = actual
        self._check()
        self._out_theirs = [t.theirs for t in spec.outputs]
        self._out_ours = [t.ours for t in spec.outputs]
        self._in = {t.ours: t for t in spec.inputs}

    # ------------------------------------------------------------------ validation
    def _check(self) -> None:
        path = self.spec.path
        graph_in = {i.name: i for i in self.session.get_inputs()}
        graph_out = {o.name: o for o in self.session.get_outputs()}
        declared = set()
        for role, table, tensors in (
            ("input", graph_in, self.spec.inputs),
            ("output", graph_out, self.spec.outputs),
        ):
            for t in tensors:
                declared.add(t.theirs)
                self._check_tensor(role, t, table, path)
        extra = [n for n in graph_in if n not in declared]
        if extra:
            raise ModelError(
                f"{self.spec.key}: graph input(s) {extra} are not in the contract (nothing "
                f"would feed them); declared inputs are {[t.theirs for t in self.spec.inputs]}"
                " — map them in manifest.json 'io'",
                path,
            )

    def _check_tensor(self, role: str, t: TensorSpec, table: dict, path) -> None:
        alias = "" if t.ours == t.theirs else f" (contract name '{t.ours}')"
        if t.theirs not in table:
            raise ModelError(
                f"{self.spec.key}: expected {role} tensor '{t.theirs}'{alias}, found none; "
                f"the graph's {role}s are {sorted(table)}",
                path,
            )
        arg = table[t.theirs]
        found = _ORT_TYPES.get(arg.type, arg.type)
        if found != t.dtype:
            raise ModelError(
                f"{self.spec.key}: {role} '{t.theirs}'{alias}: expected dtype {t.dtype}, "
                f"found {found}",
                path,
            )
        got = _dims(arg.shape)
        want = list(t.shape)
        if len(got) != len(want):
            raise ModelError(
                f"{self.spec.key}: {role} '{t.theirs}'{alias}: expected rank {len(want)} "
                f"{want}, found rank {len(got)} {list(arg.shape)}",
                path,
            )
        for axis, (g, w) in enumerate(zip(got, want)):
            if isinstance(w, int) and g is not None and g != w:
                raise ModelError(
                    f"{self.spec.key}: {role} '{t.theirs}'{alias}: expected shape {want}, "
                    f"found {list(arg.shape)} (axis {axis})",
                    path,
                )
            if isinstance(w, str) and w != "*" and g is not None and role == "input":
                raise ModelError(
                    f"{self.spec.key}: input '{t.theirs}'{alias}: axis {axis} must be dynamic "
                    f"({w}), found fixed size {g} in {list(arg.shape)}; re-export with a "
                    "dynamic axis",
                    path,
                )

    def input_shape(self, ours: str) -> List[object]:
        """The graph's own shape of input ``ours`` (None for dynamic axes)."""
        name = self._in[ours].theirs
        for i in self.session.get_inputs():
            if i.name == name:
                return _dims(i.shape)
        raise KeyError(ours)

    # ------------------------------------------------------------------ running
    def run(self, feeds: Mapping[str, np.ndarray]) -> Dict[str, np.ndarray]:
        """Run with inputs in our names; returns outputs in our names."""
        missing = [k for k in self._in if k not in feeds]
        if missing:
            raise ModelError(f"{self.spec.key}: internal error, inputs {missing} not fed",
                             self.spec.path)
        theirs = {}
        for ours, t in self._in.items():
            arr = feeds[ours]
            if arr.dtype != np.dtype(t.dtype):
                arr = arr.astype(t.dtype)
            theirs[t.theirs] = arr
        if self.options.trace_shapes:
            self.stats.shapes.append({k: tuple(v.shape) for k, v in feeds.items()})
        t0, c0 = time.perf_counter(), time.thread_time()
        outs = self.session.run(self._out_theirs, theirs)
        self.stats.seconds += time.perf_counter() - t0
        self.stats.thread_cpu_seconds += time.thread_time() - c0
        self.stats.calls += 1
        return dict(zip(self._out_ours, outs))
