"""Plans: a workflow expanded into tasks (stage x item) with their input bindings, and
the state of each task in a cache (done / stale / missing / failed / corrupt) with reasons.

A task's cache key is the sha256 of the canonical JSON of
``{stage, version, params, item, attrs, inputs: {artifact: output hash}, device, data}``
(``device`` only for stages that declare ``uses_device``; ``data``, stat fingerprints of
the files and folders the params and attributes name, only where they name some). Input hashes are the content
hashes recorded in upstream manifests, so a key is known only once every upstream task is
done; until then the task is *pending* on them.

A value that ``shares`` another (``[axes.scene.lego_fast] shares = "lego"``) reuses that value's
tasks wherever they would compute the same thing: a task whose params and key attributes equal
those of its *twin* (the same item with the shared value in place of this one) and whose inputs
come from the twin's own upstream tasks is keyed as the twin (``Task.key_item``) and runs after
it: the two have one key and one cache entry (the same SfM, the same masks), computed once,
by the twin. Elsewhere (a training with another recipe, and everything downstream of it) the
task is keyed as itself, so its entries are those it would have without ``shares``; but where
only the twin changed (an override added to the twin alone), the entry the twin computed for
exactly this task's config is still served (``Task.alt_key_item``, :func:`entry_key`) rather
than computed again.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence

from .cache import Cache, EntryCheck
from .hashing import canonical_json, sha256_text
from .items import Item
from .stage import Stage
from .workflow import ResolvedParams, Workflow


@dataclass(frozen=True)
class Binding:
    """One input of a task: the producing tasks of artifact ``name``."""

    name: str
    producer: str
    sources: tuple[int, ...]  # task indices in the plan
    fan_in: bool  # True: the stage receives {Item: path}; False: exactly one path


@dataclass(frozen=True)
class Task:
    index: int
    stage: Stage
    item: Item
    params: ResolvedParams
    bindings: tuple[Binding, ...]
    #: the twin task this one is keyed as and runs after (``shares``), else None
    twin: Optional[int] = None
    key_item: Optional[Item] = None
    #: a task of a value that shares another, not keyed as its twin (the twin's config moved
    #: away): the twin's item, under which an entry for exactly this task's config may have been
    #: computed while the two were the same; such an entry is served (:func:`entry_key`)
    alt_key_item: Optional[Item] = None

    @property
    def id(self) -> str:
        return f"{self.stage.name}[{self.item.label}]"

    @property
    def deps(self) -> tuple[int, ...]:
        seen: dict[int, None] = {}
        for b in self.bindings:
            for s in b.sources:
                seen[s] = None
        if self.twin is not None:
            seen[self.twin] = None
        return tuple(seen)


class Plan:
    """Every task of a workflow, in an order where producers come first."""

    def __init__(self, workflow: Workflow):
        self.workflow = workflow
        self.tasks: list[Task] = []
        self.by_stage: dict[str, list[int]] = {}
        # (producer stage, shared axes) -> {projected item: [task index]}
        index: dict[tuple[str, tuple[str, ...]], dict[Item, list[int]]] = {}
        wf = workflow
        for name in wf.graph.order:
            stage = wf.stages[name]
            level = wf.levels[name]
            producers = []
            for art in stage.inputs:
                prod = wf.graph.producer[art]
                shared = tuple(a for a in wf.levels[prod] if a in level)
                fan_in = shared != wf.levels[prod]
                table = index.get((prod, shared))
                if table is None:
                    table = {}
                    for t in self.by_stage[prod]:
                        table.setdefault(self.tasks[t].item.project(shared), []).append(t)
                    index[(prod, shared)] = table
                producers.append((art, prod, shared, fan_in, table))
            ids = self.by_stage.setdefault(name, [])
            items = wf.axes.instances(level)
            # values that share another come after it, so that a twin is always planned first
            twins = {item: wf.axes.twin(item) for item in items}
            own: dict[Item, Task] = {}
            for item in sorted(items, key=lambda i: twins[i] is not None):
                bindings = []
                for art, prod, shared, fan_in, table in producers:
                    sources = tuple(table.get(item.project(shared), ()))
                    bindings.append(Binding(art, prod, sources, fan_in))
                params = wf.params_for(name, item)
                twin = own.get(twins[item]) if twins[item] is not None else None
                alt = None
                if twin is not None and not self._same_work(twin, item, params, bindings):
                    if wf.key_attrs(twin.item, name) == wf.key_attrs(item, name):
                        alt = twin.key_item or twin.item
                    twin = None
                task = Task(len(self.tasks), stage, item, params, tuple(bindings),
                            twin=twin.index if twin is not None else None,
                            key_item=twin.item if twin is not None else None, alt_key_item=alt)
                self.tasks.append(task)
                ids.append(task.index)
                own[item] = task
        self.dependents: list[list[int]] = [[] for _ in self.tasks]
        for task in self.tasks:
            for dep in task.deps:
                self.dependents[dep].append(task.index)

    def _same_work(self, twin: Task, item: Item, params: ResolvedParams,
                   bindings: Sequence[Binding]) -> bool:
        """Whether a task of ``item`` would compute what ``twin`` computes: the same key params
        and key attributes, and inputs from the twin's own sources (or their twins)."""
        wf = self.workflow
        if twin.params.key_json != params.key_json or \
                wf.key_attrs(twin.item, twin.stage.name) != wf.key_attrs(item, twin.stage.name):
            return False
        for mine, theirs in zip(bindings, twin.bindings):
            sources = tuple(self.tasks[s].twin if self.tasks[s].twin is not None else s for s in mine.sources)
            if sources != theirs.sources:
                return False
        return True

    def find(self, stage: str, item_id: str) -> Task:
        for i in self.by_stage.get(stage, []):
            if self.tasks[i].item.id == item_id:
                return self.tasks[i]
        raise KeyError(f"no task {stage}[{item_id}]")


class OutputTable:
    """Outputs (manifest ``outputs`` sections) of finished tasks, by task index."""

    def __init__(self, plan: Plan):
        self.item_ids = [t.item.id for t in plan.tasks]
        self.outputs: list[Optional[Mapping[str, Any]]] = [None] * len(plan.tasks)
        self.entry_dirs: list[Optional[Path]] = [None] * len(plan.tasks)

    def __call__(self, index: int) -> Optional[Mapping[str, Any]]:
        return self.outputs[index]

    def set(self, index: int, outputs: Mapping[str, Any], entry_dir: Path) -> None:
        self.outputs[index] = outputs
        self.entry_dirs[index] = entry_dir

    def hashes(self, task: Task) -> Optional[dict[str, Any]]:
        """``{artifact: hash}`` (fan-in: ``{artifact: {item id: hash}}``), or None while
        some source task has no outputs yet."""
        result: dict[str, Any] = {}
        outputs = self.outputs
        for b in task.bindings:
            if b.fan_in:
                gathered = {}
                for s in b.sources:
                    outs = outputs[s]
                    if outs is None:
                        return None
                    gathered[self.item_ids[s]] = outs[b.name]["sha256"]
                result[b.name] = gathered
            else:
                outs = outputs[b.sources[0]]
                if outs is None:
                    return None
                result[b.name] = outs[b.name]["sha256"]
        return result

    def input_paths(self, task: Task, items: Sequence[Item]) -> dict[str, Any]:
        """The paths a stage's ``run`` receives (fan-in: ``{Item: path}``)."""
        paths: dict[str, Any] = {}
        for b in task.bindings:
            def path_of(s: int) -> Path:
                return self.entry_dirs[s] / self.outputs[s][b.name]["path"]  # type: ignore
            if b.fan_in:
                paths[b.name] = {items[s]: path_of(s) for s in b.sources}
            else:
                paths[b.name] = path_of(b.sources[0])
        return paths


def key_document(task: Task, workflow: Workflow, hashes: Mapping[str, Any]) -> dict[str, Any]:
    stage = task.stage
    doc = {
        "stage": stage.name,
        "version": stage.version,
        "params": task.params.key_json,
        "item": (task.key_item or task.item).to_json(),
        "attrs": workflow.key_attrs(task.item, stage.name),
        "inputs": hashes,
        "device": workflow.settings.device if stage.uses_device else None,
    }
    data = workflow.data_fingerprints(task.item, task.params.value, stage.name)
    if data:  # (absent when no path is named: such keys are unchanged)
        doc["data"] = data
    return doc


def task_key(task: Task, workflow: Workflow, hashes: Mapping[str, Any]) -> str:
    return sha256_text(canonical_json(key_document(task, workflow, hashes)))


def entry_key(task: Task, workflow: Workflow, hashes: Mapping[str, Any], cache: Cache,
              forced: bool = False) -> tuple[str, dict[str, Any], EntryCheck]:
    """``(key, key document, check)`` of the entry a task uses: its own key, or, for a task of a
    value that shares another whose own entry is not done, the key under the twin's item
    (:attr:`Task.alt_key_item`) when that entry is done (computed by the twin while the two were
    the same; a forced task always takes its own)."""
    doc = key_document(task, workflow, hashes)
    key = sha256_text(canonical_json(doc))
    check = cache.check(task.stage.name, key)
    if check.state != "done" and task.alt_key_item is not None and not forced:
        alt_doc = {**doc, "item": task.alt_key_item.to_json()}
        alt = sha256_text(canonical_json(alt_doc))
        alt_check = cache.check(task.stage.name, alt)
        if alt_check.state == "done":
            return alt, alt_doc, alt_check
    return key, doc, check


# -- inspection: state of every task without running anything -------------------------

@dataclass
class TaskState:
    """What the cache holds for one task of a plan.

    ``state``: done (entry valid) | failed (last attempt with this key failed) |
    corrupt (entry unusable, will be recomputed) | stale (this slot ran before with a
    different key) | missing (never ran) . ``pending`` lists upstream tasks that are not
    done (so the key is not known yet).
    """

    task: Task
    state: str
    key: Optional[str] = None
    check: Optional[EntryCheck] = None
    manifest: Optional[dict] = None  # entry manifest (done) or failure manifest (failed)
    entry_dir: Optional[Path] = None
    reasons: list[str] = field(default_factory=list)
    pending: list[int] = field(default_factory=list)
    hashes: Optional[dict] = None

    @property
    def stage(self) -> str:
        return self.task.stage.name

    @property
    def item(self) -> Item:
        return self.task.item

    @property
    def log_path(self) -> Optional[Path]:
        """The log of a done entry or of the last failure with this key."""
        if self.entry_dir is None or self.state not in ("done", "failed"):
            return None
        from .cache import inside

        rel = (self.manifest or {}).get("log", "log.txt")
        return self.entry_dir / rel if inside(self.entry_dir, rel) else None

    def output(self, name: str) -> Path:
        """Path of output artifact ``name`` of a done entry."""
        if self.state != "done" or self.manifest is None or self.entry_dir is None:
            raise KeyError(f"{self.task.id} is {self.state}, it has no outputs")
        from .cache import inside

        rel = self.manifest["outputs"][name]["path"]
        if not inside(self.entry_dir, rel):  # (checked when the entry was read; a failure record too)
            raise KeyError(f"{self.task.id}: output {name!r} points outside its entry")
        return self.entry_dir / rel


def inspect(plan: Plan, cache: Cache, with_reasons: bool = True) -> list[TaskState]:
    """The state of every task; reads manifests (and refs when ``with_reasons``)."""
    wf = plan.workflow
    wf.use_cache(cache.root, writable=False)  # (a run's writable memo is kept)
    table = OutputTable(plan)
    states: list[TaskState] = []
    for task in plan.tasks:
        hashes = table.hashes(task)
        if hashes is None:
            pending = [d for d in task.deps if table.outputs[d] is None]
            st = TaskState(task, "missing", pending=pending)
            if with_reasons:
                ref = cache.read_ref(wf.id, task.stage.name, task.item.id)
                if ref is not None:
                    st.state = "stale"
                    st.reasons = diff_reasons(task, wf, ref, None)
                up = ", ".join(plan.tasks[d].id for d in pending[:3])
                more = f" and {len(pending) - 3} more" if len(pending) > 3 else ""
                st.reasons.append(f"waits on {up}{more}")
            states.append(st)
            continue
        key, _, check = entry_key(task, wf, hashes, cache)
        st = TaskState(task, "missing", key, check, hashes=hashes)
        if check.state == "done":
            st.state, st.manifest = "done", check.manifest
            st.entry_dir = cache.entry_dir(task.stage.name, key)
            table.set(task.index, check.manifest["outputs"], st.entry_dir)  # type: ignore
        elif check.state == "corrupt":
            st.state = "corrupt"
            st.reasons = [f"corrupt entry: {check.reason}"]
            st.entry_dir = cache.entry_dir(task.stage.name, key)
        else:
            failed = cache.load_failed(task.stage.name, key)
            if failed is not None:
                st.state, st.manifest = "failed", failed
                st.entry_dir = cache.failed_dir(task.stage.name, key)
                st.reasons = [f"failed before: {failed.get('error', {}).get('summary', '?')}"]
            elif with_reasons:
                ref = cache.read_ref(wf.id, task.stage.name, task.item.id)
                if ref is not None and ref.get("key") != key:
                    st.state = "stale"
                    st.reasons = diff_reasons(task, wf, ref, hashes)
                else:
                    st.reasons = ["new"] if ref is None else ["entry missing from the cache"]
        states.append(st)
    return states


class _Unset:
    def __repr__(self) -> str:
        return "<unset>"


_UNSET = _Unset()


def _short(value: Any) -> str:
    if value is _UNSET:
        return "<unset>"
    text = canonical_json(value)
    return text if len(text) <= 40 else text[:37] + "..."


def diff_reasons(task: Task, wf: Workflow, ref: Mapping[str, Any],
                 hashes: Optional[Mapping[str, Any]]) -> list[str]:
    """Why ``task`` differs from the slot's last run ``ref`` (cheapest checks first)."""
    reasons = []
    if ref.get("version") != task.stage.version:
        reasons.append(f"version changed ({ref.get('version')} -> {task.stage.version})")
    old, new = ref.get("params") or {}, task.params.key_json
    if old != new:
        changed = _dict_diff(old, new)
        reasons.append("params changed (" + ", ".join(changed[:4])
                       + (", ..." if len(changed) > 4 else "") + ")")
    if task.stage.uses_device and ref.get("device") != wf.settings.device:
        reasons.append(f"device changed ({ref.get('device')} -> {wf.settings.device})")
    if hashes is not None and ref.get("inputs") != hashes:
        old_in = ref.get("inputs") or {}
        names = [n for n in hashes if old_in.get(n) != hashes[n]]
        reasons.append("input changed (" + ", ".join(names) + ")")
    if "data" in ref:
        old_data = ref.get("data") or {}
        new_data = wf.data_fingerprints(task.item, task.params.value, task.stage.name)
        changed = sorted(k for k in set(old_data) | set(new_data) if old_data.get(k) != new_data.get(k))
        if changed:
            reasons.append("data on disk changed (" + ", ".join(changed[:3]) + ")")
    if not reasons and hashes is not None:
        reasons.append("item attributes changed")
    return reasons


def _dict_diff(old: Mapping[str, Any], new: Mapping[str, Any], prefix: str = "") -> list[str]:
    out = []
    for k in sorted(set(old) | set(new)):
        a, b = old.get(k, _UNSET), new.get(k, _UNSET)
        if a == b:
            continue
        if isinstance(a, Mapping) and isinstance(b, Mapping):
            out += _dict_diff(a, b, f"{prefix}{k}.")
        else:
            out.append(f"{prefix}{k}: {_short(a)} -> {_short(b)}")
    return out
