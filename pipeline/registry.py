"""A registry: the stages a program offers, plus optional schemas for axis attributes.

The engine never discovers stages; a program builds one registry from explicit lists (in
this project ``stages/registry.py``). An *axis schema* is a frozen dataclass that types the
attributes of an axis's values (e.g. ``scene``: ``path: Path``, ``kind: str``), so that
paths resolve relative to the workflow file and unknown keys are errors. Fields whose
``metadata`` has ``{"cache_key": False}`` (display labels) stay out of cache keys.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Iterable, Mapping, Optional

from .errors import StageSpecError
from .graph import Graph
from .stage import Stage


class Registry:
    """Stages by name and axis schemas by axis name; the stage graph is validated eagerly."""

    def __init__(self, stages: Iterable[Stage] = (),
                 axis_schemas: Optional[Mapping[str, type]] = None):
        self.stages: dict[str, Stage] = {}
        self.axis_schemas: dict[str, type] = {}
        #: optional ``device_check(device)`` raising ``ValueError`` when this machine cannot
        #: compute on the workflow's ``device`` (a CPU-only torch asked for ``cuda``): a local
        #: run calls it before any task that uses the device runs (the program sets it)
        self.device_check: Optional[Callable[[str], None]] = None
        #: names no axis value may take (lower case): the files the program writes beside the
        #: folders values become (the program sets it)
        self.reserved_names: frozenset[str] = frozenset()
        #: named tables an axis value may start from (``preset = "NAME"``): axis -> name ->
        #: table, resolved when a workflow loads (the program sets them)
        self.presets: dict[str, dict[str, dict]] = {}
        for stage in stages:
            self.add(stage)
        for axis, schema in (axis_schemas or {}).items():
            self.add_axis_schema(axis, schema)

    def add(self, stage: Stage) -> Stage:
        if not isinstance(stage, Stage):
            raise StageSpecError(f"expected a pipeline Stage, got {stage!r}")
        if stage.name in self.stages and self.stages[stage.name] is not stage:
            raise StageSpecError(f"stage {stage.name!r} is registered twice")
        self.stages[stage.name] = stage
        return stage

    def add_axis_schema(self, axis: str, schema: type) -> None:
        if not (isinstance(schema, type) and dataclasses.is_dataclass(schema)
                and schema.__dataclass_params__.frozen):  # type: ignore[attr-defined]
            raise StageSpecError(f"axis {axis!r}: schema must be a frozen dataclass type, "
                                 f"got {schema!r}")
        if self.axis_schemas.get(axis, schema) is not schema:
            raise StageSpecError(f"axis {axis!r} has two schemas: "
                                 f"{self.axis_schemas[axis].__name__} and {schema.__name__}")
        self.axis_schemas[axis] = schema

    def graph(self) -> Graph:
        """The DAG of every registered stage (raises on cycles, duplicates, missing inputs)."""
        return Graph(list(self.stages.values()))
