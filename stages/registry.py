"""The stages the ``cobgs`` program offers, collected into one pipeline registry.

To add a stage: write ``stages/<name>.py`` exposing ``STAGE = Stage(...)`` (or
``STAGES = (...)`` for several) and add ``"stages.<name>"`` to :data:`STAGE_MODULES`.
A module may also expose ``AXIS_SCHEMAS = {"scene": SceneAttrs}`` to type the attributes
of an axis's values. Keep module-level imports light (import ``cobgs``/torch inside the
stage's ``run``): every ``cobgs run`` / ``status`` imports all stage modules.

Extra stage modules (experiments, test fixtures) can be added without editing this file
by listing them, comma-separated, in the environment variable ``COBGS_STAGE_MODULES``.
A fixture that brings a whole DAG of its own (the engine's toy stages reuse the names
``train``, ``refine``, ...) sets ``COBGS_BUILTIN_STAGES=0`` to leave the built-in stages out.
"""

from __future__ import annotations

import importlib
import os
from pathlib import Path
from typing import Iterable, Optional

from pipeline import PipelineError, Registry, Stage

#: Modules holding the built-in stages, in the order `cobgs stages` lists them.
STAGE_MODULES: tuple[str, ...] = (
    "stages.dataset",
    "stages.sfm",
    "stages.train",
    "stages.masks",
    "stages.refine",
    "stages.segment",
    "stages.evaluate",
    "stages.summary",
    "stages.heldout",
)

EXTRA_MODULES_ENV = "COBGS_STAGE_MODULES"
BUILTIN_ENV = "COBGS_BUILTIN_STAGES"


def stage_modules(extra: Optional[Iterable[str]] = None) -> list[str]:
    env = [m.strip() for m in os.environ.get(EXTRA_MODULES_ENV, "").split(",") if m.strip()]
    builtin = [] if os.environ.get(BUILTIN_ENV, "1").strip() == "0" else list(STAGE_MODULES)
    return builtin + env + list(extra or ())


def load_registry(extra: Optional[Iterable[str]] = None) -> Registry:
    """A registry of every stage in :data:`STAGE_MODULES` (plus ``extra`` and the modules
    named in ``$COBGS_STAGE_MODULES``)."""
    registry = Registry()
    for name in stage_modules(extra):
        try:
            module = importlib.import_module(name)
        except ImportError as exc:
            raise PipelineError(f"cannot import stage module {name!r}: {exc}") from exc
        stages = list(getattr(module, "STAGES", ()))
        if hasattr(module, "STAGE"):
            stages.append(module.STAGE)
        if not stages:
            raise PipelineError(f"stage module {name!r} defines neither STAGE nor STAGES")
        for stage in stages:
            if not isinstance(stage, Stage):
                raise PipelineError(f"stage module {name!r}: {stage!r} is not a pipeline Stage")
            registry.add(stage)
        for axis, schema in getattr(module, "AXIS_SCHEMAS", {}).items():
            registry.add_axis_schema(axis, schema)
    registry.device_check = check_device
    registry.reserved_names = reserved_names()
    registry.presets = load_presets()
    return registry


#: The presets workflows refer to by name (``[axes.method.X] preset = "NAME"``): one file.
PRESETS_FILE = Path(__file__).resolve().parent / "presets.toml"


def load_presets(path: Path = PRESETS_FILE) -> dict[str, dict[str, dict]]:
    """``{axis: {name: table}}`` from :data:`PRESETS_FILE` (each top-level table an axis, each of
    its tables a preset). A preset may hold stage overrides and attributes, not the workflow's
    own ``only`` / ``shares`` / ``preset``.

    Raises:
        PipelineError: the file is not such TOML (naming it and the preset).
    """
    import tomllib

    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise PipelineError(f"{path}: cannot read the presets: {exc}") from None
    out: dict[str, dict[str, dict]] = {}
    for axis, presets in raw.items():
        if not isinstance(presets, dict) or not all(isinstance(t, dict) for t in presets.values()):
            raise PipelineError(f"{path}: [{axis}] must hold one table per preset")
        for name, table in presets.items():
            bad = sorted({"only", "shares", "preset"} & set(table))
            if bad:
                raise PipelineError(f"{path}: preset {axis}.{name} sets {bad}, which only a workflow's own value may")
        out[axis] = presets
    return out

def reserved_names() -> frozenset[str]:
    """Every file name of the artifact catalog (``cobgs.configs.Files``: ``train.json``,
    ``summary.json`` ...): an axis value named so would collide with it in an export, where
    values are folders beside those files."""
    from cobgs.configs import Files

    return frozenset(v.lower() for k, v in vars(Files).items() if k.isupper() and isinstance(v, str) and "." in v)


def check_device(device: str) -> None:
    """Whether this machine's torch computes on ``device`` (imports torch: only called for a
    device other than the CPU, before a run's first task on it).

    Raises:
        ValueError: a CUDA device on a torch without CUDA, or an index past the GPUs seen.
    """
    import torch

    if not device.startswith("cuda"):
        return
    if not torch.cuda.is_available():
        why = "is built without CUDA" if torch.version.cuda is None else "sees no CUDA device"
        raise ValueError(f"this torch ({torch.__version__}) {why}; run with --set device=cpu, or install a CUDA "
                         "build of torch on a machine with a GPU")
    _, _, index = device.partition(":")
    if index and int(index) >= torch.cuda.device_count():
        raise ValueError(f"this machine has {torch.cuda.device_count()} CUDA device(s) (cuda:0 ...); "
                         f"there is no {device}")
