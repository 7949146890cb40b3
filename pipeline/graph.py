"""The stage DAG: edges from matching artifact names, order from :mod:`graphlib`."""

from __future__ import annotations

import graphlib
from typing import Iterable, Mapping, Sequence

from .errors import CycleError, DuplicateOutputError, MissingInputError, unknown_key_hint
from .stage import Stage


class Graph:
    """Stages wired by artifact name; validated on construction.

    Raises:
        DuplicateOutputError: a stage name or an output artifact appears twice.
        MissingInputError: an input artifact that no stage produces.
        CycleError: the stages depend on each other in a cycle (names listed).
    """

    def __init__(self, stages: Sequence[Stage]):
        self.stages: dict[str, Stage] = {}
        self.producer: dict[str, str] = {}  # artifact -> stage name
        for stage in stages:
            if stage.name in self.stages:
                raise DuplicateOutputError(f"stage {stage.name!r} is declared twice")
            self.stages[stage.name] = stage
            for out in stage.outputs:
                if out in self.producer:
                    raise DuplicateOutputError(
                        f"artifact {out!r} is produced by both stage {self.producer[out]!r} "
                        f"and stage {stage.name!r}; every artifact needs exactly one producer")
                self.producer[out] = stage.name
        self.upstream: dict[str, tuple[str, ...]] = {}
        for stage in stages:
            deps = []
            for art in stage.inputs:
                if art not in self.producer:
                    raise MissingInputError(
                        f"stage {stage.name!r} needs artifact {art!r}, which no stage produces"
                        + (unknown_key_hint(art, self.producer) if self.producer else ""))
                if self.producer[art] not in deps:
                    deps.append(self.producer[art])
            self.upstream[stage.name] = tuple(deps)
        self.order = self._toposort()
        self.downstream: dict[str, tuple[str, ...]] = {
            n: tuple(m for m in self.order if n in self.upstream[m]) for n in self.order}

    def _toposort(self) -> tuple[str, ...]:
        rank = {name: i for i, name in enumerate(self.stages)}
        sorter = graphlib.TopologicalSorter(self.upstream)
        try:
            sorter.prepare()
        except graphlib.CycleError as exc:
            # graphlib lists each node before the one that depends on it, the first
            # repeated at the end: already the direction data flows.
            raise CycleError(list(exc.args[1])) from None
        order: list[str] = []
        while sorter.is_active():
            ready = sorted(sorter.get_ready(), key=rank.__getitem__)  # stable: declaration order
            order.extend(ready)
            sorter.done(*ready)
        return tuple(order)

    def check_names(self, names: Iterable[str], what: str) -> list[str]:
        """``names`` checked against the stages, for ``--only`` and friends."""
        out = []
        for name in names:
            if name not in self.stages:
                raise MissingInputError(f"{what}: unknown stage {name!r}"
                                        + unknown_key_hint(name, self.stages))
            out.append(name)
        return out

    def ancestors(self, names: Iterable[str], include: bool = True) -> set[str]:
        seen: set[str] = set(names) if include else set()
        todo = list(names)
        while todo:
            for dep in self.upstream[todo.pop()]:
                if dep not in seen:
                    seen.add(dep)
                    todo.append(dep)
        return seen

    def descendants(self, names: Iterable[str], include: bool = True) -> set[str]:
        seen: set[str] = set(names) if include else set()
        todo = list(names)
        while todo:
            for down in self.downstream[todo.pop()]:
                if down not in seen:
                    seen.add(down)
                    todo.append(down)
        return seen

    def subgraph(self, names: Iterable[str]) -> "Graph":
        """The stages ``names`` and everything they depend on, in a new graph."""
        keep = self.ancestors(names)
        return Graph([s for n, s in self.stages.items() if n in keep])

    def as_mapping(self) -> Mapping[str, tuple[str, ...]]:
        return dict(self.upstream)
