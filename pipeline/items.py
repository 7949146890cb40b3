"""Axes and items: how one workflow fans out.

A workflow declares ordered *axes* (``scene``, ``method``, optionally ``object``), each
with named values. A stage's *level* is a subset of the axes; it runs once per *instance*
of that level, an :class:`Item` holding one value per axis of the level (the empty item,
``Item.root()``, is the single instance of the per-workflow level ``()``).

An axis may be *nested* in an earlier one (``object`` within ``scene``): its values are
then declared per parent value, and a level holding it must hold its parent too.

A task at level ``L`` consumes an artifact produced at level ``P`` from every instance of
``P`` that agrees with it on the shared axes ``L & P``. When ``P`` is a subset of ``L``
that is exactly one instance (fan-out: a per-scene x method task reads its scene's
artifact); otherwise it is several, and the task receives ``{Item: path}`` (fan-in: a
per-workflow report reads every scene x method).
"""

from __future__ import annotations

import fnmatch
import re
from dataclasses import dataclass, field
from typing import Any, Iterable, Mapping, Optional, Sequence

from .errors import WorkflowError

# "/" "," "=" are item-id syntax; names become folder names (export, report), so no path
# separator, no leading "." (".", "..", hidden files), no control character, no trailing space.
VALUE_RE = re.compile(r"^[^/\\,=\s.\x00-\x1f\x7f](?:[^/\\,=\x00-\x1f\x7f]*[^/\\,=\s\x00-\x1f\x7f])?$")


@dataclass(frozen=True)
class Axis:
    """One axis: its values with their attributes, optionally nested in a parent axis.

    ``values`` maps value name -> attributes (flat axes); for a nested axis it maps parent
    value -> {value name -> attributes}.
    """

    name: str
    values: Mapping[str, Any]
    parent: Optional[str] = None

    def names(self, parent_value: Optional[str] = None) -> list[str]:
        if self.parent is None:
            return list(self.values)
        return list(self.values.get(parent_value, {}))

    def attrs(self, value: str, parent_value: Optional[str] = None) -> Any:
        table = self.values if self.parent is None else self.values[parent_value]
        return table[value]


@dataclass(frozen=True)
class Item:
    """One instance of a level: ``(axis, value)`` pairs in workflow axis order.

    Equality and hashing use the pairs only; ``attrs`` maps each axis to the attributes of
    its value (a dataclass when the axis has a registered schema, else a dict).
    """

    pairs: tuple[tuple[str, str], ...]
    attrs: Mapping[str, Any] = field(default_factory=dict, compare=False, hash=False, repr=False)

    @staticmethod
    def root() -> "Item":
        return Item(())

    @property
    def id(self) -> str:
        """``"lego/no_bags"``; ``""`` for the per-workflow item."""
        return "/".join(v for _, v in self.pairs)

    @property
    def label(self) -> str:
        """The id, or ``(workflow)`` for the root item (for display)."""
        return self.id or "(workflow)"

    @property
    def axes(self) -> tuple[str, ...]:
        return tuple(a for a, _ in self.pairs)

    @property
    def values(self) -> dict[str, str]:
        return dict(self.pairs)

    def __getitem__(self, axis: str) -> str:
        for a, v in self.pairs:
            if a == axis:
                return v
        raise KeyError(f"item {self.label!r} has no axis {axis!r} (it has {list(self.axes)})")

    def project(self, axes: Iterable[str]) -> "Item":
        keep = set(axes)
        return Item(tuple(p for p in self.pairs if p[0] in keep),
                    {a: v for a, v in self.attrs.items() if a in keep})

    def to_json(self) -> dict[str, str]:
        return dict(self.pairs)

    def __str__(self) -> str:
        return self.label


class Axes:
    """The ordered axes of a workflow and the instances of any level.

    ``only`` restricts where a value takes part: ``{(axis, slot): ItemFilter}`` (``slot`` is
    the value's name, ``parent/value`` for a nested axis). A full item holding a restricted
    value exists only when the value's filter selects it; an item of a smaller level holding
    one exists only when it is the projection of such a full item (so no task runs for a
    combination nothing downstream asks for). Items holding no restricted value are the
    plain product, as without restrictions.

    ``shares`` maps ``(axis, value)`` to another value of the same (flat) axis whose tasks the
    value reuses wherever they would compute the same thing (:meth:`twin`; the plan decides
    where, :class:`pipeline.plan.Plan`).
    """

    def __init__(self, axes: Sequence[Axis], only: Optional[Mapping[tuple[str, str], "ItemFilter"]] = None,
                 shares: Optional[Mapping[tuple[str, str], str]] = None):
        self._axes = {a.name: a for a in axes}
        self.order = tuple(a.name for a in axes)
        self.only = dict(only or {})
        self.shares = dict(shares or {})
        self._instances: dict[tuple[str, ...], list[Item]] = {}

    def twin(self, item: Item) -> Optional[Item]:
        """``item`` with each value that ``shares`` another replaced by that value (the pairs
        only: its attributes stay ``item``'s); None when it holds no such value."""
        if not self.shares:
            return None
        pairs = tuple((a, self.shares.get((a, v), v)) for a, v in item.pairs)
        return Item(pairs, item.attrs) if pairs != item.pairs else None

    def __contains__(self, name: str) -> bool:
        return name in self._axes

    def __getitem__(self, name: str) -> Axis:
        return self._axes[name]

    def normalize_level(self, level: Sequence[str], owner: str,
                        source: Optional[str] = None) -> tuple[str, ...]:
        """``level`` in workflow order, checked: known axes, nested axes with their parent."""
        for name in level:
            if name not in self._axes:
                raise WorkflowError(f"{owner} runs per {tuple(level)} but the workflow has no "
                                    f"axis {name!r} (its axes: {list(self.order) or 'none'}); "
                                    f"declare values as [axes.{name}.NAME]", source, "axes")
            parent = self._axes[name].parent
            if parent is not None and parent not in level:
                raise WorkflowError(f"{owner} runs per {tuple(level)}: axis {name!r} is nested "
                                    f"in {parent!r}, so the level must include {parent!r}",
                                    source, "axes")
        return tuple(a for a in self.order if a in level)

    def slot(self, axis: str, pairs: Iterable[tuple[str, str]]) -> tuple[str, str]:
        """Key of ``axis``'s value in ``pairs`` among per-value tables (``parent/value`` when nested)."""
        values = dict(pairs)
        parent = self._axes[axis].parent
        return (axis, f"{values[parent]}/{values[axis]}" if parent is not None else values[axis])

    def _restricted(self, item: Item) -> list["ItemFilter"]:
        return [f for a, _ in item.pairs if (f := self.only.get(self.slot(a, item.pairs))) is not None]

    def instances(self, level: tuple[str, ...]) -> list[Item]:
        """Every item of ``level`` (already normalised), in declaration order."""
        cached = self._instances.get(level)
        if cached is not None:
            return cached
        items = self._product(level)
        if self.only:
            if level == self.order:
                items = [i for i in items if all(f.selects_full(i) for f in self._restricted(i))]
            else:
                shadows = {f.project(level) for f in self.instances(self.order)}
                items = [i for i in items if not self._restricted(i) or i in shadows]
        self._instances[level] = items
        return items

    def _product(self, level: tuple[str, ...]) -> list[Item]:
        partial: list[tuple[tuple[tuple[str, str], ...], dict[str, Any]]] = [((), {})]
        for name in level:
            axis = self._axes[name]
            grown = []
            for pairs, attrs in partial:
                parent_value = dict(pairs).get(axis.parent) if axis.parent else None
                for value in axis.names(parent_value):
                    grown.append((pairs + ((name, value),),
                                  {**attrs, name: axis.attrs(value, parent_value)}))
            partial = grown
        return [Item(pairs, attrs) for pairs, attrs in partial]

    def all_items(self) -> list[Item]:
        return self.instances(self.order)


@dataclass(frozen=True)
class ItemFilter:
    """``--items`` patterns: ``lego``, ``scene=lego``, ``lego/no_*`` (fnmatch globs).

    A pattern is ``/``-separated parts; a part ``axis=glob`` constrains that axis, a bare
    ``glob`` must match the value of some axis. An item is selected when every part of some
    pattern holds.
    """

    patterns: tuple[tuple[tuple[Optional[str], str], ...], ...]

    @staticmethod
    def parse(text: str, axes: Axes) -> "ItemFilter":
        patterns = []
        for raw in (p.strip() for p in text.split(",")):
            if not raw:
                continue
            parts = []
            for part in raw.split("/"):
                axis, _, glob = part.rpartition("=")
                if axis and axis not in axes:
                    raise WorkflowError(f"--items {raw!r}: unknown axis {axis!r} "
                                        f"(axes: {list(axes.order)})")
                parts.append((axis or None, glob))
            patterns.append(tuple(parts))
        if not patterns:
            raise WorkflowError("--items: expected at least one item pattern")
        return ItemFilter(tuple(patterns))

    def _matches_part(self, item: Item, axis: Optional[str], glob: str) -> Optional[bool]:
        """True/False, or None when the part names an axis the item does not have."""
        if axis is not None:
            if axis not in item.axes:
                return None
            return fnmatch.fnmatchcase(item[axis], glob)
        return any(fnmatch.fnmatchcase(v, glob) for _, v in item.pairs)

    def selects_full(self, item: Item) -> bool:
        return any(all(self._matches_part(item, a, g) for a, g in pattern)
                   for pattern in self.patterns)

    def unmatched(self, full_items: Sequence[Item]) -> list[str]:
        """Patterns that select nothing (a typo, most likely)."""
        out = []
        for pattern in self.patterns:
            one = ItemFilter((pattern,))
            if not any(one.selects_full(f) for f in full_items):
                out.append("/".join(f"{a}={g}" if a else g for a, g in pattern))
        return out


def agrees(a: Item, b: Item) -> bool:
    """Whether two items hold the same value on every axis they share."""
    bv = b.values
    return all(bv.get(axis, v) == v for axis, v in a.pairs)


#: Longest axis value name: names become folder and file names (export, report; an object
#: folder holds ``<scene>_<method>_<object>...`` files), which most filesystems cap at 255 bytes.
MAX_VALUE_BYTES = 100


def invisible_chars(name: str) -> list[str]:
    """The invisible formatting characters of ``name`` (U+202E that reverses the text after
    it, U+FEFF, zero-width spaces, line separators ...: Unicode categories Cf, Zl, Zp), as
    ``U+XXXX``: a folder named with them reads as another name."""
    import unicodedata

    return [f"U+{ord(c):04X}" for c in name if unicodedata.category(c) in ("Cf", "Zl", "Zp")]


def check_value_name(name: str, axis: str, source: str) -> None:
    if isinstance(name, str) and invisible_chars(name):
        raise WorkflowError(f"value name {name!r} holds invisible formatting characters "
                            f"({', '.join(invisible_chars(name)[:3])}): names become folder names, which would read "
                            "as another name", source, f"axes.{axis}")
    if isinstance(name, str) and len(name.encode("utf-8")) > MAX_VALUE_BYTES:
        raise WorkflowError(f"value name {name[:40]!r}... is {len(name.encode('utf-8'))} bytes long; at most "
                            f"{MAX_VALUE_BYTES} (names become folder and file names)", source, f"axes.{axis}")
    if not isinstance(name, str) or not VALUE_RE.match(name):
        raise WorkflowError(f"value name {name!r} may not be empty, start with a space or '.', end "
                            "with a space, or contain '/', '\\', ',', '=' or a control character "
                            "(names become folder names)", source, f"axes.{axis}")

