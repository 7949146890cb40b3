"""Stage declarations: what a stage needs, makes, and at which level of the workflow it runs.

A stage is *declared*, not discovered::

    @dataclass(frozen=True)
    class TrainParams:
        iterations: int = 30_000

    def run_train(ctx: StageContext, inputs: Mapping[str, Any]) -> Mapping[str, Path]:
        out = ctx.out_dir / "scene.ply"
        ...                                    # read inputs["poses"], write out
        return {"scene": out}

    TRAIN = Stage(name="train", version=1, level=("scene",), inputs=("poses",),
                  outputs=("scene",), params=TrainParams, run=run_train, uses_device=True)

``level`` names the workflow axes the stage fans out over: ``("scene",)`` runs once per
scene, ``("scene", "method")`` once per scene x method, ``()`` once per workflow (a fan-in
over every item). Bump ``version`` by hand whenever the stage's behaviour changes; it is part
of the cache key (hashing source code makes reruns spurious, so the engine does not).
"""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable, Mapping, Optional, Union

from .errors import StageSpecError

if TYPE_CHECKING:  # pragma: no cover
    from .context import StageContext
    from .values import Settings

NAME_RE = re.compile(r"^[a-z][a-z0-9_]*$")
#: Words that mean something else on the command line (``--force all``) or in a workflow.
RESERVED_NAMES = frozenset({"all", "device", "settings", "axes", "params", "workflow", "only", "shares"})


@dataclass(frozen=True)
class NoParams:
    """Params of a stage that has none."""


@dataclass(frozen=True)
class Resources:
    """What one task of a stage needs from the machine.

    ``gpus`` is only requested when the workflow's device is CUDA (see
    :meth:`Stage.resources_for`); a CPU run of a GPU-capable stage asks for none.
    """

    cpus: float = 1.0
    gpus: float = 0.0
    memory_gb: float = 0.0  # 0 = undeclared; forwarded to Ray's ``memory`` when > 0

    def __post_init__(self) -> None:
        for name in ("cpus", "gpus", "memory_gb"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or isinstance(value, bool) or value < 0:
                raise StageSpecError(f"Resources.{name} must be a number >= 0, got {value!r}")


RunFn = Callable[["StageContext", Mapping[str, Any]], Mapping[str, Any]]
ResourcesSpec = Union[Resources, Callable[["Settings"], Resources]]


@dataclass(frozen=True)
class Stage:
    """One step of the DAG.

    Args:
        name: lower_snake_case, unique in a registry.
        version: bumped by hand when the behaviour changes (part of the cache key).
        run: ``run(ctx, inputs) -> {output name: path inside ctx.out_dir}``. ``inputs`` maps
            each input artifact name to the path of the finished upstream artifact
            (read-only), or, for a fan-in, to ``{Item: path}`` over every gathered item.
        inputs: artifact names consumed (each produced by exactly one other stage).
        outputs: artifact names produced (at least one; unique across the registry).
        params: a frozen dataclass type; its defaults are overridden by the workflow.
        level: the workflow axes this stage runs over (``()`` = once per workflow).
        uses_device: the stage computes on the workflow's ``device``; the device then
            enters the cache key, and a CUDA device requests ``gpus``.
        resources: a :class:`Resources`, or a function of the workflow settings giving one.
        description: one line for ``cobgs stages``.
        check: optional ``check(params)`` raising ``ValueError`` for values the params
            class cannot judge alone (they need the library, e.g. the config the params
            become); called once per distinct params for the tasks a run will execute,
            before any of them runs, so a bad value stops the run before hours of upstream
            work, with the file and key that set it. It may import heavy modules: a fully
            cached run never calls it.
        key_params: optional ``key_params(params, params_json) -> dict``: the part of the
            params JSON that enters the cache key, for a stage whose params hold sections
            that only some of its modes read (e.g. the thresholds of one mask route): a
            change to a section the task does not read then recomputes nothing. It must
            keep everything the task's outputs depend on; the manifest still records all.
        precheck: optional ``precheck(params, item, inputs)`` raising ``ValueError`` for a task
            that cannot succeed, judged from its item and cheap inputs (a click file naming
            views the dataset does not have). Called in the driver for each task a run will
            execute: when the run is planned, with those of ``precheck_inputs`` that are
            already done, and again as soon as the rest are, before the run starts anything
            else. A refusal at plan time stops the run before any task; later, no new task
            starts (hours of SfM and training are not spent on a task that must fail).
            ``inputs`` maps each available precheck input to its path.
        precheck_inputs: the inputs (a subset of ``inputs``, not fan-in) ``precheck`` reads.
    """

    name: str
    version: Union[int, str]
    run: RunFn
    inputs: tuple[str, ...] = ()
    outputs: tuple[str, ...] = ()
    params: type = NoParams
    level: tuple[str, ...] = ()
    uses_device: bool = False
    resources: ResourcesSpec = field(default_factory=Resources)
    description: str = ""
    check: Optional[Callable[[Any], None]] = None
    key_params: Optional[Callable[[Any, Mapping[str, Any]], Mapping[str, Any]]] = None
    precheck: Optional[Callable[[Any, Any, Mapping[str, Any]], None]] = None
    precheck_inputs: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        where = f"stage {self.name!r}"
        if not isinstance(self.name, str) or not NAME_RE.match(self.name):
            raise StageSpecError(f"stage name must match {NAME_RE.pattern}, got {self.name!r}")
        if self.name in RESERVED_NAMES:
            raise StageSpecError(f"{where}: the name is reserved ({sorted(RESERVED_NAMES)})")
        if isinstance(self.version, bool) or not isinstance(self.version, (int, str)) or (
            isinstance(self.version, str) and not self.version.strip()
        ):
            raise StageSpecError(f"{where}: version must be an int or a non-empty string, "
                                 f"got {self.version!r}")
        if not callable(self.run):
            raise StageSpecError(f"{where}: run must be callable, got {type(self.run).__name__}")
        if self.key_params is not None and not callable(self.key_params):
            raise StageSpecError(f"{where}: key_params must be callable or None")
        if self.precheck is not None and not callable(self.precheck):
            raise StageSpecError(f"{where}: precheck must be callable or None")
        object.__setattr__(self, "precheck_inputs", tuple(self.precheck_inputs))
        stray = [n for n in self.precheck_inputs if n not in tuple(self.inputs)]
        if stray:
            raise StageSpecError(f"{where}: precheck_inputs {stray} are not among its inputs {list(self.inputs)}")
        for attr in ("inputs", "outputs", "level"):
            value = getattr(self, attr)
            if isinstance(value, str) or not isinstance(value, (tuple, list)):
                raise StageSpecError(f"{where}: {attr} must be a tuple of names, got {value!r}")
            object.__setattr__(self, attr, tuple(value))
            for name in getattr(self, attr):
                if not isinstance(name, str) or not NAME_RE.match(name):
                    raise StageSpecError(
                        f"{where}: {attr} entry must match {NAME_RE.pattern}, got {name!r}")
            dup = sorted({n for n in getattr(self, attr) if getattr(self, attr).count(n) > 1})
            if dup:
                raise StageSpecError(f"{where}: {attr} lists {dup} more than once")
        if not self.outputs:
            raise StageSpecError(f"{where}: declares no outputs; a stage must produce an "
                                 "artifact to be cached")
        both = sorted(set(self.inputs) & set(self.outputs))
        if both:
            raise StageSpecError(f"{where}: {both} are both inputs and outputs")
        if not (isinstance(self.params, type) and dataclasses.is_dataclass(self.params)):
            raise StageSpecError(f"{where}: params must be a dataclass type, got {self.params!r}")
        if not self.params.__dataclass_params__.frozen:  # type: ignore[attr-defined]
            raise StageSpecError(f"{where}: params dataclass {self.params.__name__} must be "
                                 "frozen (@dataclass(frozen=True))")
        if not (isinstance(self.resources, Resources) or callable(self.resources)):
            raise StageSpecError(f"{where}: resources must be Resources or a function of the "
                                 f"settings, got {self.resources!r}")

    def resources_for(self, settings: "Settings") -> Resources:
        """The resources one task asks for under ``settings`` (GPUs only on CUDA)."""
        res = self.resources(settings) if callable(self.resources) else self.resources
        if not isinstance(res, Resources):
            raise StageSpecError(f"stage {self.name!r}: resources function returned "
                                 f"{res!r}, expected Resources")
        on_gpu = self.uses_device and settings.device.startswith("cuda")
        if not on_gpu and res.gpus:
            res = dataclasses.replace(res, gpus=0.0)
        elif on_gpu and not res.gpus:
            res = dataclasses.replace(res, gpus=1.0)
        return res
