"""A small table model (columns, cells) with best-value marking; the template renders it.

Cells carry their display text and a raw sort value, so the page's JavaScript sorts by
numbers, not by formatted strings. Best values are marked per group (per scene, say) and
only among measured numbers: quoted paper numbers and empty cells never take part, and a
group with a single measured value marks nothing (a lone row is not "best").
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Optional, Sequence

from .fmt import finite


@dataclass
class Column:
    """Attributes:
        key: record key of the value.
        label: header text.
        fmt: raw value -> display text.
        numeric: sort as numbers (right-aligned).
        better: "max" or "min" to mark the best value, None for no marking.
        title: header tooltip (units, definition).
        quoted: the column holds numbers quoted from the paper (styled apart, never best).
    """

    key: str
    label: str
    fmt: Callable[[Any], str] = lambda v: "" if v is None else str(v)
    numeric: bool = True
    better: Optional[str] = None
    title: str = ""
    quoted: bool = False

    def __post_init__(self) -> None:
        if self.better not in (None, "max", "min"):
            raise ValueError(f"column {self.key!r}: better must be 'max', 'min' or None, got {self.better!r}")


@dataclass
class Cell:
    text: str
    sort: Any = ""
    classes: list[str] = field(default_factory=list)
    title: str = ""
    href: Optional[str] = None
    sub: str = ""  # a second, smaller line under the text (method options, say)

    @property
    def cls(self) -> str:
        return " ".join(self.classes)


@dataclass
class Row:
    cells: list[Cell]
    classes: list[str] = field(default_factory=list)

    @property
    def cls(self) -> str:
        return " ".join(self.classes)


@dataclass
class Table:
    id: str
    caption: str
    columns: list[Column]
    rows: list[Row]
    notes: list[str] = field(default_factory=list)


def best_indices(values: Sequence[Any], better: str) -> set[int]:
    """Indices of the best finite values (ties all win). Empty with fewer than two values
    or when every value is the same: marking all rows would single nothing out."""
    nums = [(i, finite(v)) for i, v in enumerate(values)]
    nums = [(i, v) for i, v in nums if v is not None]
    if len(nums) < 2:
        return set()
    target = max(v for _, v in nums) if better == "max" else min(v for _, v in nums)
    tol = 1e-12 * max(1.0, abs(target))
    best = {i for i, v in nums if abs(v - target) <= tol}
    return set() if len(best) == len(nums) else best


def build_table(table_id: str, caption: str, columns: Sequence[Column], records: Sequence[dict],
                group_by: Optional[str] = None, notes: Sequence[str] = ()) -> Table:
    """A :class:`Table` of ``records`` (dicts keyed by column keys).

    Optional record keys: ``_row_class`` (list of row classes), ``_title`` / ``_href`` /
    ``_text`` / ``_sub`` / ``_class`` (``{column key: value}`` per cell), ``_nobest`` (the row takes no
    part in best-value marking, e.g. an incomplete aggregate).
    """
    groups: dict[Any, list[int]] = {}
    for i, r in enumerate(records):
        groups.setdefault(r.get(group_by) if group_by else None, []).append(i)
    best: dict[tuple[int, str], bool] = {}
    for col in columns:
        if col.better is None or col.quoted:
            continue
        for members in groups.values():
            eligible = [i for i in members if not records[i].get("_nobest")]
            for j in best_indices([records[i].get(col.key) for i in eligible], col.better):
                best[(eligible[j], col.key)] = True
    rows = []
    for i, r in enumerate(records):
        cells = []
        for col in columns:
            v = r.get(col.key)
            text = r.get("_text", {}).get(col.key)
            if text is None:
                text = col.fmt(v)
            classes = list(r.get("_class", {}).get(col.key, []))
            if col.numeric:
                classes.append("num")
            if col.quoted:
                classes.append("quoted")
            if best.get((i, col.key)):
                classes.append("best")
            sort = finite(v) if col.numeric else (v if isinstance(v, str) else text)
            cells.append(Cell(text=text, sort="" if sort is None else sort, classes=classes,
                              title=r.get("_title", {}).get(col.key, ""), href=r.get("_href", {}).get(col.key),
                              sub=r.get("_sub", {}).get(col.key, "")))
        rows.append(Row(cells, list(r.get("_row_class", []))))
    return Table(table_id, caption, list(columns), rows, list(notes))
