"""Read a workflow's results back from the pipeline cache (nothing is run or written).

Everything the report shows comes from here: the state of every task
(:func:`pipeline.entries`) and the small JSON files the stages leave in their artifacts
(the layouts are documented in stages/_common.py). Artifacts are found by *name*
(``metrics``, ``refined``, ``segmentation``, ``scene``, ``dataset``, ``heldout``) through
the workflow's graph, so the report follows the stages wherever the DAG puts them.

A result whose chain is incomplete keeps a :class:`Problem` naming the first task that
failed (or that never ran) and its log, so the report can show the gap instead of a number.
"""

from __future__ import annotations

from cobgs.configs import Files
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

from cobgs.data.spec import DatasetSpec
from cobgs.evaluate.protocols import ORACLE_METHOD, oracle_choice

from .errors import ReportError

#: artifact -> the JSON file that describes it
DESCRIPTORS = {"metrics": Files.METRICS, "refined": Files.REFINE, "segmentation": Files.SEGMENT,
               "scene": Files.TRAIN, "dataset": Files.DATASET, "heldout": Files.HELDOUT}


def read_artifact_json(folder: Path, name: str, owner: str) -> dict:
    """``folder/name`` as JSON; a clear :class:`ReportError` naming ``owner`` otherwise."""
    path = Path(folder) / name
    try:
        with open(path, encoding="utf-8") as f:
            data = json.load(f)
    except FileNotFoundError:
        raise ReportError(f"{owner}: {path} is missing although the cache entry is complete "
                          "(run `cobgs cache verify --fix`, then rerun the workflow)") from None
    except (OSError, ValueError) as exc:
        raise ReportError(f"{owner}: {path} is unreadable: {exc}") from None
    if not isinstance(data, dict):
        raise ReportError(f"{owner}: {path} should hold a JSON object, got {type(data).__name__}")
    return data


@dataclass
class TaskRecord:
    """One stage x item of the workflow as the cache knows it."""

    stage: str
    item: Any  # pipeline.Item
    state: str  # done | failed | corrupt | stale | missing
    key: Optional[str]
    reasons: list[str]
    manifest: Optional[dict]
    entry_dir: Optional[Path]
    log_path: Optional[Path]

    @property
    def item_id(self) -> str:
        return self.item.label

    @property
    def values(self) -> dict:
        return dict(self.item.values)

    def out(self, artifact: str) -> Optional[Path]:
        """The folder of a finished output artifact, or None."""
        if self.state != "done" or not self.manifest or self.entry_dir is None:
            return None
        rec = self.manifest.get("outputs", {}).get(artifact)
        return None if rec is None else self.entry_dir / rec["path"]

    @property
    def error(self) -> str:
        if self.state == "failed" and self.manifest:
            return str((self.manifest.get("error") or {}).get("summary", "failed (no summary recorded)"))
        return "; ".join(self.reasons)


@dataclass
class Problem:
    """Why a result has no numbers: the first task of its chain that is not done."""

    stage: str
    item_id: str
    state: str
    message: str
    log_path: Optional[Path]


@dataclass
class Result:
    """One scene x method x object: its metrics row and what the report draws from it."""

    scene: str
    method: str
    object: str
    row: Optional[dict] = None  # metrics.json "row"
    per_view: dict = field(default_factory=dict)  # view -> {iou, acc, biou, ...}
    skipped: dict = field(default_factory=dict)  # view -> reason
    empty_gt: dict = field(default_factory=dict)  # view -> how an empty GT mask was scored
    psnr_per_view: dict = field(default_factory=dict)
    refine: Optional[dict] = None  # refine.json
    refine_params: Optional[dict] = None  # the refine task's resolved params
    refine_dir: Optional[Path] = None
    segment: Optional[dict] = None  # segment.json
    segment_dir: Optional[Path] = None
    tasks: dict = field(default_factory=dict)  # stage -> TaskRecord of this item's chain
    problem: Optional[Problem] = None

    @property
    def ok(self) -> bool:
        return self.row is not None

    @property
    def method_kind(self) -> str:
        """A name of :data:`cobgs.refine.methods.REGISTRY` (from the refine params or the row)."""
        if self.refine_params and "method" in self.refine_params:
            return str(self.refine_params["method"])
        return str((self.row or {}).get("method_kind") or (self.refine or {}).get("method") or "")


@dataclass
class Heldout:
    folder: Path
    info: dict  # heldout.json


@dataclass
class SceneRecord:
    name: str
    dataset: Optional[dict] = None  # dataset.json
    train: Optional[dict] = None  # train.json
    train_dir: Optional[Path] = None
    train_task: Optional[TaskRecord] = None
    heldout: dict = field(default_factory=dict)  # object -> Heldout
    dataset_dir: Optional[Path] = None  # the dataset artifact (cameras, for turntables)
    poses_dir: Optional[Path] = None  # the SfM artifact, where the scene has one

    @property
    def protocol(self) -> str:
        return DatasetSpec(self.dataset or {}).protocol if self.dataset else ""


@dataclass
class RunData:
    workflow: Any  # pipeline.Workflow
    cache_dir: Path
    tasks: list[TaskRecord]
    results: list[Result]
    scenes: dict[str, SceneRecord]
    methods: list[str]  # in workflow order
    # (dataset dir, poses dir or None) -> (training cameras, background): the command layer
    # hands it in (reports read no artifact layout of the stages; turntables, 3D viewers)
    scene_cameras: Optional[Any] = None

    def cameras(self, scene: "SceneRecord") -> tuple[list, tuple]:
        """(training cameras, background) of a scene, through :attr:`scene_cameras`."""
        if self.scene_cameras is None:
            raise ReportError("turntables and 3D viewers need the scenes' cameras: build the report through "
                              "`cobgs report` (stages.commands.report.build_report), which hands them in")
        return self.scene_cameras(scene.dataset_dir, scene.poses_dir)

    @property
    def failed(self) -> list[TaskRecord]:
        return [t for t in self.tasks if t.state in ("failed", "corrupt")]

    @property
    def not_done(self) -> list[TaskRecord]:
        return [t for t in self.tasks if t.state != "done"]

    def counts(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for t in self.tasks:
            out[t.state] = out.get(t.state, 0) + 1
        return out


def _tasks(workflow, cache_dir: Path) -> list[TaskRecord]:
    from pipeline import entries

    out = []
    for rec in entries(workflow, cache_dir):
        out.append(TaskRecord(stage=rec.stage, item=rec.item, state=rec.state, key=rec.key, reasons=list(rec.reasons),
                        manifest=rec.manifest, entry_dir=rec.entry_dir, log_path=rec.log_path))
    return out


def _axis_names(workflow, axis: str, parent_value: Optional[str] = None) -> list[str]:
    if axis not in workflow.axes:
        return []
    return workflow.axes[axis].names(parent_value)


def _with_later_params(params: dict, defaults: dict) -> dict:
    """``params`` with the COB-GS fields added after cache entries were written filled in with
    the value those entries ran with (:func:`cobgs.configs.with_later_values`, the one owner of
    that rule; the refine stage's key leaves them out at that value, so an old entry is served
    for them): a method's old and new entries then read alike (otherwise its options "vary by
    scene"). Only where the stage's own defaults know the section (another program's refine
    stage is left alone)."""
    from cobgs.configs import RefineConfig, with_later_values

    sec = params.get("cobgs")
    known = defaults.get("cobgs") or {}
    if isinstance(sec, dict) and known:
        filled = with_later_values(RefineConfig, sec)
        params["cobgs"] = {k: v for k, v in filled.items() if k in sec or k in known}
    return params


def _refine_defaults(workflow) -> dict:
    from pipeline.params import to_json

    stage = workflow.graph.producer.get("refined")
    return to_json(workflow.stages[stage].params()) if stage is not None else {}


def collect(workflow, cache_dir: os.PathLike | str) -> RunData:
    """Everything the report needs about ``workflow`` (a loaded :class:`pipeline.Workflow`)
    from the cache at ``cache_dir``."""
    cache_dir = Path(cache_dir)
    tasks = _tasks(workflow, cache_dir)
    producer = workflow.graph.producer
    refine_defaults = _refine_defaults(workflow)
    by_stage: dict[str, dict[Any, TaskRecord]] = {}
    for t in tasks:
        by_stage.setdefault(t.stage, {})[t.item] = t

    def task_for(artifact: str, item) -> Optional[TaskRecord]:
        stage = producer.get(artifact)
        if stage is None:
            return None
        return by_stage.get(stage, {}).get(item.project(workflow.levels[stage]))

    def load(task: Optional[TaskRecord], artifact: str) -> tuple[Optional[dict], Optional[Path]]:
        folder = task.out(artifact) if task is not None else None
        if folder is None:
            return None, None
        return read_artifact_json(folder, DESCRIPTORS[artifact], f"{task.stage}[{task.item_id}]"), folder

    scenes: dict[str, SceneRecord] = {}
    for name in _axis_names(workflow, "scene"):
        sc = SceneRecord(name)
        for t in by_stage.get(producer.get("dataset", ""), {}).values():
            if t.values.get("scene") == name:
                raw, sc.dataset_dir = load(t, "dataset")
                sc.dataset = DatasetSpec(raw) if raw is not None else None
        for t in by_stage.get(producer.get("poses", ""), {}).values():
            if t.values.get("scene") == name and t.state == "done":
                sc.poses_dir = t.out("poses")
        for t in by_stage.get(producer.get("scene", ""), {}).values():
            if t.values.get("scene") == name:
                sc.train_task = t
                sc.train, sc.train_dir = load(t, "scene")
        for t in by_stage.get(producer.get("heldout", ""), {}).values():
            if t.values.get("scene") == name:
                info, folder = load(t, "heldout")
                if info is not None:
                    sc.heldout[t.values.get("object", "")] = Heldout(folder, info)
        scenes[name] = sc

    results = []
    metrics_stage = producer.get("metrics")
    if metrics_stage is not None:
        chain = [s for s in workflow.graph.order if s in workflow.graph.ancestors([metrics_stage])]
        for mt in by_stage.get(metrics_stage, {}).values():
            v = mt.values
            r = Result(scene=v.get("scene", ""), method=v.get("method", ""), object=v.get("object", ""))
            for s in chain:
                t = by_stage.get(s, {}).get(mt.item.project(workflow.levels[s]))
                if t is not None:
                    r.tasks[s] = t
            r.problem = _first_problem(r.tasks, chain)
            metrics, _ = load(mt, "metrics")
            if metrics is not None:
                r.row = dict(metrics.get("row") or {})
                details = metrics.get("details") or {}
                r.per_view = dict(details.get("per_view") or {})
                r.skipped = dict(details.get("skipped") or {})
                r.empty_gt = dict(details.get("empty_gt") or {})
                r.psnr_per_view = dict(metrics.get("psnr_per_view") or {})
            rt = task_for("refined", mt.item)
            r.refine, r.refine_dir = load(rt, "refined")
            if rt is not None and rt.manifest is not None and rt.state == "done":
                r.refine_params = _with_later_params(dict(rt.manifest.get("params") or {}), refine_defaults)
            st = task_for("segmentation", mt.item)
            r.segment, r.segment_dir = load(st, "segmentation")
            results.append(r)
    results += _oracle_results(results)
    order = _order(workflow)
    results.sort(key=lambda r: (order["scene"].get(r.scene, 1e9), order["method"].get(r.method, 1e9),
                                order["object"].get((r.scene, r.object), 1e9), r.scene, r.method, r.object))
    methods = _axis_names(workflow, "method")
    if any(r.method == ORACLE_METHOD for r in results):
        methods.append(ORACLE_METHOD)
    return RunData(workflow=workflow, cache_dir=cache_dir, tasks=tasks, results=results, scenes=scenes,
                   methods=methods)


def _oracle_results(results: list) -> list:
    """FlashSplat at its best bias per scene (:func:`cobgs.evaluate.protocols.oracle_choice`): copies
    of the chosen item's results under the method ``flashsplat_oracle``."""
    import dataclasses

    rows = [dict(r.row, scene=r.scene, method=r.method, object=r.object, method_kind=r.method_kind)
            for r in results if r.ok]
    choice = oracle_choice(rows)
    out = []
    for r in results:
        if r.ok and choice.get(r.scene) == r.method:
            out.append(dataclasses.replace(r, method=ORACLE_METHOD, row=dict(r.row, oracle_choice=r.method)))
    return out


def _first_problem(tasks: dict, chain: list[str]) -> Optional[Problem]:
    """The earliest failed task of the chain; else the earliest one that is not done."""
    pending = [tasks[s] for s in chain if s in tasks and tasks[s].state != "done"]
    if not pending:
        return None
    failed = [t for t in pending if t.state in ("failed", "corrupt")]
    t = (failed or pending)[0]
    return Problem(stage=t.stage, item_id=t.item_id, state=t.state, message=t.error or t.state,
                   log_path=t.log_path if t.state == "failed" else None)


def _order(workflow) -> dict[str, dict]:
    scenes = _axis_names(workflow, "scene")
    objects: dict = {}
    if "object" in workflow.axes:
        ax = workflow.axes["object"]
        for s in scenes:
            for i, o in enumerate(ax.names(s) if ax.parent else ax.names()):
                objects[(s, o)] = i
    return {"scene": {s: i for i, s in enumerate(scenes)},
            "method": {m: i for i, m in enumerate(_axis_names(workflow, "method"))},
            "object": objects}
