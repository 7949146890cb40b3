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


#: What each column means, shown under every table that has it (and as its tooltip).
GLOSSARY = {
    "iou": "intersection over union of the predicted and the ground-truth object mask on the held-out "
           "views (TP / (TP + FP + FN)); mIoU: its mean over objects, then scenes (NVOS: over tasks; "
           "LERF-mask: over prompts)",
    "biou": "boundary IoU: IoU of the two masks' boundary bands (mask minus its erosion, width 2 % of "
            "the image diagonal): how clean the object's outline is; mBIoU: its mean",
    "acc": "pixel accuracy ((TP + TN) / all pixels); mAcc: its mean",
    "headline": "the headline protocol (docs/method.md §5): the object's Gaussians rendered alone (label > 0.9, mask "
                "> 0.5; SA3D-GS: its own 0.1 bar) against the object's whole silhouette where the data has it "
                "(synthetic scenes, a one-object alpha matte), else against the visible GT",
    "biou_released": "released protocol: the same object-only render against the visible GT (parts another "
                     "object hides count as errors)",
    "biou_occlusion": "occlusion-aware protocol: every Gaussian rendered, the object's with their label, so "
                      "occluders hide it as in the GT, against the visible GT",
    "psnr_before_raem": "PSNR of the refined scene before RAEM's final pruning (paper Table 4 has no RAEM)",
    "psnr_delta_before_raem": "before-RAEM PSNR minus the vanilla scene's",
    "dropped": "Gaussians taken out of a peer's optimisation but kept in the scene (SA3D-GS: label <= 0 "
               "after its first pass); not deleted",
    "psnr": "peak signal-to-noise ratio (dB) of the scene the method leaves, rendered at the held-out "
            "views, against the photos",
    "psnr_delta": "ΔPSNR: the method's held-out PSNR minus the vanilla (trained, unrefined) scene's; "
                  "below 0: the refinement lost texture",
    "num_gaussians": "Gaussians in the scene (after the method)", "objects": "objects evaluated",
    "splits": "Gaussians split on the object's boundary (BAGS)",
    "pruned": "Gaussians deleted from the scene (COB-GS: the ambiguous ones RAEM removes at the end)",
    "ambiguous_final": "Gaussians still ambiguous (neither object nor background) after the last stage",
    "ambiguous": "Gaussians ambiguous in this stage (mean score between δ and 1 − δ)",
    "ambiguous_large": "ambiguous Gaussians large enough to split",
    "refine_s": "wall time of the method on one object (from the refine task's manifest)",
    "peak_rss": "peak resident memory of the task's process", "peak_gpu": "peak of PyTorch's CUDA allocator",
    "mask_route": "how the training masks were made: files, released masks, scribbles -> SAM2, text -> "
                  "Grounding DINO + SAM2", "status": "whether every task of the row finished",
    "scene": "scene", "method": "method (COB-GS, an ablation row or a peer)", "object": "object",
    "scenes": "scenes with results", "views": "held-out views scored",
    "kind": "data layout / stage kind", "protocol": "evaluation protocol: exact GT, NVOS, LERF-mask, or none "
                                                   "(own data: no ground truth)",
    "scene_type": "forward-facing or 360° (sets δ and the stage count)", "test_views": "views held out of training",
    "iterations": "training iterations", "train_s": "wall time of the 3DGS training",
    "ssim": "structural similarity of the held-out renders", "notes": "what the reader decided (e.g. a "
            "distortion dropped, names matched by sorted order)",
    "index": "stage number in the alternation", "g_start": "Gaussians at the stage's start",
    "g_end": "Gaussians at its end", "split": "Gaussians split in the stage", "loss": "mean mask loss of the stage",
    "wall_s": "wall-clock time", "cpu_s": "CPU time (user + system)", "order": "order in the plan",
    "stage": "pipeline stage", "item": "the task's scene / method / object", "state": "done, failed, stale, missing",
    "key": "cache key (hash of the stage, its params, its inputs' content and its data)", "version": "stage version",
    "host": "machine (and Ray node) that ran the task", "device": "cpu or cuda", "started": "start time",
    "log": "the task's log",
}


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
        wrap: long text that wraps within a bounded width (keeps wide tables on the page).
    """

    key: str
    label: str
    fmt: Callable[[Any], str] = lambda v: "" if v is None else str(v)
    numeric: bool = True
    better: Optional[str] = None
    title: str = ""
    quoted: bool = False
    wrap: bool = False

    def __post_init__(self) -> None:
        if not self.title:  # every column is defined on the page (glossary below its table)
            object.__setattr__(self, "title", GLOSSARY.get(self.key, ""))
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
            if col.wrap:
                classes.append("wrap")
            if best.get((i, col.key)):
                classes.append("best")
            sort = finite(v) if col.numeric else (v if isinstance(v, str) else text)
            cells.append(Cell(text=text, sort="" if sort is None else sort, classes=classes,
                              title=r.get("_title", {}).get(col.key, ""), href=r.get("_href", {}).get(col.key),
                              sub=r.get("_sub", {}).get(col.key, "")))
        rows.append(Row(cells, list(r.get("_row_class", []))))
    return Table(table_id, caption, list(columns), rows, list(notes))


def to_markdown(table: Table) -> str:
    """The table as GitHub Markdown, with the page's display text (the method's options and
    other second lines in brackets, best values in bold), caption above and notes below."""
    def esc(text: str) -> str:  # names reach tables: `a|b` must stay one cell
        return str(text).replace("\\", "\\\\").replace("|", "\\|").replace("\r", " ").replace("\n", " ")

    def cell(c: Cell) -> str:
        text = esc(c.text + (f" ({c.sub})" if c.sub else ""))
        return f"**{text}**" if "best" in c.classes and text else text

    lines = [f"**{esc(table.caption)}**", "", "| " + " | ".join(esc(c.label) for c in table.columns) + " |",
             "|" + "|".join("---:" if c.numeric else "---" for c in table.columns) + "|"]
    lines += ["| " + " | ".join(cell(c) for c in r.cells) + " |" for r in table.rows]
    if not table.rows:
        lines.append("| nothing recorded |" + " |" * (len(table.columns) - 1))
    lines += [""] + [f"{n}" for n in table.notes]
    return "\n".join(lines).rstrip() + "\n"
