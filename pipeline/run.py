"""Running a workflow: select tasks, reuse what is cached, execute the rest in dependency
order on an executor, stream one progress line per task, summarise.

Selection (all optional, combined):
  ``items``   item patterns (see items.ItemFilter); a fan-in task runs only when every
              item it gathers is selected.
  ``only``    run only these stages; other stages' entries are used when done, and a
              selected task whose upstream is not done is *blocked*.
  ``force``   recompute these stages even when cached (``("all",)``: every stage).
  ``from_stages``  recompute these stages and every stage downstream of them.
  ``verify_data``  re-read the content of every external input (data folders, mask folders,
              model folders) instead of trusting size and modification time.
The external data a forced task reads are re-read too: ``--force dataset`` after an edit that
kept a file's size and time finds the edit, and every task reading the data reruns.
A task whose upstream failed is *blocked*; other items carry on. The exit code is 0 when
everything selected is done, 1 when some task failed or was blocked, 130 on Ctrl-C.
"""

from __future__ import annotations

import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional, TextIO

from .cache import Cache, ref_record
from .errors import CacheError, ExecutorError, WorkflowError
from .execute import Job, JobResult, warnings_note
from .executors import ForkExecutor, InlineExecutor
from .items import ItemFilter, Item
from .plan import OutputTable, Plan, Task, entry_key, inspect
from .hashing import canonical_json
from .workflow import Workflow


@dataclass(frozen=True)
class RunOptions:
    """How to run a workflow (the engine-level settings come from the caller)."""

    cache_dir: Path
    package_version: str = ""
    executor: str = "local"  # "local" | "ray"
    jobs: int = 1
    address: Optional[str] = None
    only: tuple[str, ...] = ()
    from_stages: tuple[str, ...] = ()
    force: tuple[str, ...] = ()
    items: Optional[str] = None
    dry_run: bool = False
    quiet: bool = False  # no line for cached tasks
    verify_data: bool = False  # re-read every external input's content (not only the forced tasks')
    local_gpus: int = 1  # GPU tasks that may run at once with --jobs N

    def __post_init__(self) -> None:
        if self.executor not in ("local", "ray"):
            raise ExecutorError(f"unknown executor {self.executor!r}; expected local or ray")
        if not isinstance(self.jobs, int) or self.jobs < 1:
            raise ExecutorError(f"--jobs must be an integer >= 1, got {self.jobs!r}")


@dataclass
class Outcome:
    """What happened to one task in a run. ``state``: cached | done | failed | blocked |
    interrupted | reused (not selected, used from the cache) | unavailable."""

    state: str
    wall_s: float = 0.0
    note: str = ""
    log_path: Optional[str] = None
    key: Optional[str] = None


@dataclass
class RunSummary:
    plan: Plan
    outcomes: dict[int, Outcome] = field(default_factory=dict)
    interrupted: bool = False
    wall_s: float = 0.0
    total: int = 0  # tasks the run set out to settle (selected and their upstream)
    stopped: str = ""  # why the run stopped starting tasks (a full disk), "" when it did not

    def tasks_in(self, *states: str) -> list[Task]:
        return [self.plan.tasks[i] for i, o in sorted(self.outcomes.items()) if o.state in states]

    @property
    def exit_code(self) -> int:
        if self.interrupted:
            return 130
        return 1 if self.stopped or self.tasks_in("failed", "blocked", "unavailable") else 0


@dataclass(frozen=True)
class Selection:
    relevant: list[int]  # selected tasks and their upstream, in plan order
    selected: frozenset[int]
    forced: frozenset[int]
    notes: tuple[str, ...] = ()


def select(plan: Plan, options: RunOptions) -> Selection:
    wf = plan.workflow
    graph = wf.graph
    only = set(graph.check_names(options.only, "--only"))
    force_all = "all" in options.force
    force = set(graph.check_names([f for f in options.force if f != "all"], "--force"))
    from_ = graph.descendants(graph.check_names(options.from_stages, "--from"))
    notes = []
    by_items: Optional[set[int]] = None
    if options.items:
        filt = ItemFilter.parse(options.items, wf.axes)
        full = [f for f in wf.axes.all_items() if filt.selects_full(f)]
        bad = filt.unmatched(wf.axes.all_items())
        if bad:
            raise WorkflowError(f"--items: {', '.join(bad)} matches no item (items: "
                                + ", ".join(i.id for i in wf.axes.all_items()[:10]) + ")")
        projections: dict[tuple[str, ...], set[Item]] = {}
        by_items = set()
        for task in plan.tasks:
            level = wf.levels[task.stage.name]
            if level not in projections:
                projections[level] = {f.project(level) for f in full}
            if task.item in projections[level] and all(
                    s in by_items for b in task.bindings if b.fan_in for s in b.sources):
                by_items.add(task.index)
            elif task.item in projections[level]:
                notes.append(f"{task.id} skipped: it gathers items that --items leaves out")
    selected = {t.index for t in plan.tasks
                if (by_items is None or t.index in by_items)
                and (not only or t.stage.name in only)}
    selected |= {plan.tasks[i].twin for i in selected if plan.tasks[i].twin is not None}  # its work
    relevant = set(selected)
    todo = list(selected)
    while todo:
        for dep in plan.tasks[todo.pop()].deps:
            if dep not in relevant:
                relevant.add(dep)
                todo.append(dep)
    forced = {i for i in selected
              if force_all or plan.tasks[i].stage.name in force
              or plan.tasks[i].stage.name in from_}
    # a task keyed as its forced twin is recomputed by the twin, once
    forced -= {i for i in forced if plan.tasks[i].twin in forced}
    return Selection(sorted(relevant), frozenset(selected), frozenset(forced), tuple(notes))


class Progress:
    """One line per task: ``[ k/N] stage  item  state  time  note``."""

    def __init__(self, plan: Plan, total: int, stream: TextIO, quiet: bool):
        self.stream, self.quiet, self.total, self.count = stream, quiet, total, 0
        tasks = plan.tasks
        self.w_stage = max([len(t.stage.name) for t in tasks] + [5])
        self.w_item = min(max([len(t.item.label) for t in tasks] + [4]), 40)
        self.w_num = len(str(total))

    def line(self, task: Task, state: str, seconds: Optional[float] = None, note: str = "",
             final: bool = True) -> None:
        if final:
            self.count += 1
        if self.quiet and state in ("cached", "reused") and not note.startswith("WARNING"):
            return
        num = f"[{self.count:>{self.w_num}}/{self.total}]" if final else " " * (2 * self.w_num + 3)
        secs = f"{seconds:8.2f} s" if seconds is not None else " " * 10
        text = (f"{num} {task.stage.name:<{self.w_stage}}  {task.item.label:<{self.w_item}}  "
                f"{state:<11} {secs}  {note}").rstrip()
        print(text, file=self.stream, flush=True)


def _make_executor(options: RunOptions) -> Any:
    if options.executor == "ray":
        return _LazyRay(options.address)
    return InlineExecutor() if options.jobs == 1 else ForkExecutor(options.jobs)


class _LazyRay:
    """The Ray executor, connected when the first task is submitted: a run with nothing to
    compute (every task cached) never reaches for the cluster."""

    name = "ray"
    submitted_state = "queued"

    def __init__(self, address: Optional[str]):
        self.address = address
        self._ex: Any = None

    def capacity(self) -> Optional[int]:
        return None

    def submit(self, job: Job, resources: Any) -> None:
        if self._ex is None:
            from .ray_executor import RayExecutor

            self._ex = RayExecutor(self.address)
        self._ex.submit(job, resources)

    def running(self) -> int:
        return self._ex.running() if self._ex is not None else 0

    def wait(self) -> list[JobResult]:
        return self._ex.wait() if self._ex is not None else []

    def interrupt(self) -> list[JobResult]:
        return self._ex.interrupt() if self._ex is not None else []

    def close(self) -> None:
        if self._ex is not None:
            self._ex.close()


def run_workflow(workflow: Workflow, options: RunOptions, stream: Optional[TextIO] = None,
                 executor: Any = None) -> RunSummary:
    """Run (or with ``options.dry_run``, describe) ``workflow``; see the module docstring.

    Progress lines and the summary go to ``stream`` (default: standard output).
    """
    t0 = time.perf_counter()
    stream = stream if stream is not None else sys.stdout
    cache = Cache(options.cache_dir)
    workflow.use_cache(cache.root, writable=False)  # (made writable below, once the cache is)
    plan = Plan(workflow)
    sel = select(plan, options)
    if options.verify_data:
        workflow.verify_data()
    elif sel.forced:
        workflow.verify_data({p for i in sel.forced for p in workflow.data_paths(
            plan.tasks[i].item, plan.tasks[i].params.value, plan.tasks[i].stage.name).values()})
    if options.dry_run:
        check_tasks(plan, sel, cache)
        return dry_run(plan, sel, cache, stream, t0)
    prechecks = check_tasks(plan, sel, cache)
    check_device(plan, sel, cache, options)
    read_only = False
    try:
        cache.ensure()
    except CacheError:
        if not _all_done(plan, sel, cache):
            raise
        read_only = True  # everything is cached: serve it without writing a byte
        print(f"the cache {cache.root} is read-only; every task is cached, so it is served as it is "
              "(nothing recorded)", file=stream)
    if not read_only:
        workflow.use_cache(cache.root, writable=True)
        if free_bytes(cache.root) < MIN_FREE_BYTES:
            raise CacheError(disk_full_message(cache.root))
        try:
            cache.note_workflow(workflow.id, workflow.path, workflow.name)
        except OSError as exc:
            raise CacheError(f"{cache.root}: cannot write to the cache: {exc}") from None
    for note in sel.notes:
        print(note, file=stream)
    executor = executor or _make_executor(options)
    try:
        return _Scheduler(plan, sel, cache, options, executor, stream, read_only, prechecks).run(t0)
    finally:
        executor.close()


def _all_done(plan: Plan, sel: Selection, cache: Cache) -> bool:
    """Whether every task this run would settle is done in the cache (and none forced)."""
    if sel.forced:
        return False
    states = {st.task.index: st.state for st in inspect(plan, cache, with_reasons=False)}
    return all(states.get(i) == "done" for i in sel.relevant)


#: A run does not start on a cache disk with less free space than this.
MIN_FREE_BYTES = 16 << 20


def free_bytes(path: Path) -> int:
    import shutil

    try:
        return shutil.disk_usage(path).free
    except OSError:
        return 1 << 62  # unknown: let the writes say


def disk_full_message(root: Path) -> str:
    """One line: which disk is full, how much is free, what to do."""
    free = free_bytes(root)
    return (f"the disk of the cache {root} is full ({free / 2**20:.1f} MiB free): free some space "
            "(`cobgs cache gc WORKFLOW` removes entries no workflow uses) or pass --cache-dir on another disk")


def check_tasks(plan: Plan, sel: Selection, cache: Cache) -> dict[int, dict[str, int]]:
    """Run each stage's ``check`` on the params of the tasks this run will execute (not
    done in the cache, or forced), once per distinct params, before anything runs; a
    refused value raises :class:`WorkflowError` naming the file and key that set it. Then
    each such task's ``precheck`` with its precheck inputs that are done; returns, per task
    whose precheck still waits on inputs, ``{input: producing task}`` (the scheduler calls it
    again once they are done)."""
    todo = [i for i in sel.relevant if plan.tasks[i].stage.check is not None
            or plan.tasks[i].stage.precheck is not None]
    if not todo:
        return {}
    by_index = {st.task.index: st for st in inspect(plan, cache, with_reasons=False)}
    seen: set[tuple[str, str]] = set()
    waiting: dict[int, dict[str, int]] = {}
    for i in todo:
        task = plan.tasks[i]
        if by_index[i].state == "done" and i not in sel.forced:
            continue
        sig = (task.stage.name, canonical_json(task.params.json))
        if task.stage.check is not None and sig not in seen:
            seen.add(sig)
            try:
                task.stage.check(task.params.value)
            except (ValueError, TypeError) as exc:
                source, key = plan.workflow.locate(task.stage.name, task.item, str(exc))
                raise WorkflowError(f"stage {task.stage.name!r} ({task.id}): {exc}", source, key) from None
        if task.stage.precheck is None:
            continue
        ready, missing = {}, {}
        for b in task.bindings:
            if b.name not in task.stage.precheck_inputs or b.fan_in:
                continue
            st = by_index.get(b.sources[0])
            if st is not None and st.state == "done" and st.manifest and st.entry_dir is not None:
                ready[b.name] = st.entry_dir / st.manifest["outputs"][b.name]["path"]
            else:
                missing[b.name] = b.sources[0]
        message = run_precheck(task, ready)
        if message:
            source, key = plan.workflow.locate(task.stage.name, task.item, message)
            raise WorkflowError(message, source, key)
        if missing:
            waiting[i] = missing
    return waiting


def check_device(plan: Plan, sel: Selection, cache: Cache, options: RunOptions) -> None:
    """A local run on a device other than the CPU: the registry's ``device_check`` before any
    task runs, when a task this run executes computes on the device (not after hours of SfM on
    the CPU). A Ray run's workers have their own devices: not checked here."""
    device = plan.workflow.settings.device
    check = getattr(plan.workflow.registry, "device_check", None)
    if device == "cpu" or check is None or options.executor != "local":
        return
    states = {st.task.index: st.state for st in inspect(plan, cache, with_reasons=False)}
    if not any(plan.tasks[i].stage.uses_device and (states.get(i) != "done" or i in sel.forced)
               for i in sel.relevant):
        return
    try:
        check(device)
    except ValueError as exc:
        raise WorkflowError(f"settings.device = {device!r} (--set device=...): {exc}") from None


def run_precheck(task: Task, inputs: dict[str, Path]) -> str:
    """"" when ``task``'s precheck passes with ``inputs``, else what it refused."""
    try:
        task.stage.precheck(task.params.value, task.item, inputs)
    except (ValueError, TypeError, OSError) as exc:
        return f"stage {task.stage.name!r} ({task.id}): {exc}"
    except Exception as exc:  # noqa: BLE001 - a library error (the stage's own types): still one line
        return f"stage {task.stage.name!r} ({task.id}): {type(exc).__name__}: {exc}"
    return ""


class _Scheduler:
    def __init__(self, plan: Plan, sel: Selection, cache: Cache, options: RunOptions,
                 executor: Any, stream: TextIO, read_only: bool = False,
                 prechecks: Optional[dict[int, dict[str, int]]] = None):
        self.plan, self.sel, self.cache, self.options = plan, sel, cache, options
        self.prechecks = dict(prechecks or {})  # task -> {precheck input: producing task} not yet done
        self.read_only = read_only
        self.executor, self.stream = executor, stream
        self.wf = plan.workflow
        self.table = OutputTable(plan)
        self.summary = RunSummary(plan, total=len(sel.relevant))
        self.relevant = set(sel.relevant)
        self.progress = Progress(plan, len(sel.relevant), stream, options.quiet)
        self.waiting = {i: sum(1 for d in plan.tasks[i].deps) for i in sel.relevant}
        self.ready: list[int] = sorted(i for i, n in self.waiting.items() if n == 0)
        self.gpu_free = options.local_gpus
        self.jobs: dict[int, tuple[Job, float]] = {}  # running: job, gpus held
        self.task_items = [t.item for t in plan.tasks]
        self._full_by_level: dict[tuple[str, ...], dict[Item, list[Item]]] = {}

    # -- bookkeeping ---------------------------------------------------------------------
    def _settle(self, index: int, outcome: Outcome) -> None:
        self.summary.outcomes[index] = outcome
        ok = outcome.state in ("cached", "done", "reused")
        for dep in self.plan.dependents[index]:
            if dep not in self.relevant or dep in self.summary.outcomes:
                continue
            if ok:
                self.waiting[dep] -= 1
                if self.waiting[dep] == 0:
                    self.ready.append(dep)
            else:
                self._block(dep, self.plan.tasks[index])

    def _block(self, index: int, cause: Task) -> None:
        why = {"failed": "failed", "blocked": "is blocked", "unavailable": "is not done",
               "interrupted": "was interrupted"}
        cause_outcome = self.summary.outcomes[cause.index]
        state = cause_outcome.state
        outcome = Outcome("blocked", note=cause_outcome.note if state == "blocked"
                          else f"upstream {cause.id} {why.get(state, state)}")
        if state == "interrupted":
            outcome.state = "interrupted"
        else:  # before its dependents, so the lines read in dependency order
            self.progress.line(self.plan.tasks[index], "blocked", note=outcome.note)
        self._settle(index, outcome)

    def _write_ref(self, task: Task, key: str, status: str, hashes: Any) -> None:
        if self.read_only:
            return
        try:
            self.cache.write_ref(self.wf.id, task.stage.name, task.item.id, ref_record(
                key, status, task.stage.version, task.params.key_json, hashes,
                self.wf.settings.device, task.item.id,
                self.wf.data_fingerprints(task.item, task.params.value, task.stage.name)))
        except OSError as exc:  # the history is a convenience: a full disk stops the run, said once
            import errno

            if exc.errno != errno.ENOSPC:
                raise
            if not self.summary.stopped:
                self.summary.stopped = disk_full_message(self.cache.root)
                print(f"cobgs run: {self.summary.stopped}; no new task is started", file=sys.stderr)

    # -- one ready task ----------------------------------------------------------------------
    def _start(self, index: int) -> bool:
        """Handle a ready task; False if it must wait for a GPU slot."""
        task = self.plan.tasks[index]
        hashes = self.table.hashes(task)
        key, doc, check = entry_key(task, self.wf, hashes, self.cache,  # type: ignore[arg-type]
                                    forced=index in self.sel.forced)
        stage = task.stage.name
        if index not in self.sel.selected:
            if check.state == "done":
                self.table.set(index, check.manifest["outputs"],  # type: ignore[index]
                               self.cache.entry_dir(stage, key))
                self.progress.line(task, "reused", note="not selected; its entry is used")
                self._settle(index, Outcome("reused", key=key))
            else:
                outcome = Outcome("unavailable", key=key,
                                  note="not done, and not selected by --only/--items")
                self.progress.line(task, "not done", note=outcome.note)
                self._settle(index, outcome)
            return True
        if check.state == "done" and index not in self.sel.forced:
            self.table.set(index, check.manifest["outputs"],  # type: ignore[index]
                           self.cache.entry_dir(stage, key))
            ref = self.cache.read_ref(self.wf.id, stage, task.item.id)
            if ref is None or ref.get("key") != key:
                self._write_ref(task, key, "ok", hashes)
            warn = warnings_note((check.manifest or {}).get("extra"))
            self.progress.line(task, "cached", note=warn)
            self._settle(index, Outcome("cached", note=warn, key=key))
            self._prechecks_after(index)
            return True
        resources = task.stage.resources_for(self.wf.settings)
        if self.executor.capacity() is not None and resources.gpus > 0:
            if self.gpu_free < resources.gpus and self.jobs:
                return False
            self.gpu_free -= resources.gpus
        note = "forced" if index in self.sel.forced else ""
        if check.state == "corrupt":
            note = f"corrupt entry ({check.reason}), recomputing"
            print(f"warning: {task.id}: {self.cache.entry_dir(stage, key)}: {check.reason}; "
                  "recomputing", file=sys.stderr)
        job = self._job(task, key, doc, hashes, force=index in self.sel.forced)
        self.jobs[index] = (job, resources.gpus if self.executor.capacity() is not None else 0)
        # Ray queues a submitted task until a node has room: say "queued" there (its own
        # progress lines, forwarded from the node, show when it runs); a local executor
        # starts what it is given.
        self.progress.line(task, getattr(self.executor, "submitted_state", "running"), note=note, final=False)
        self.executor.submit(job, resources)
        return True

    def _provenance(self, source: int, artifact: str) -> dict[str, str]:
        out = self.table.outputs[source][artifact]  # type: ignore[index]
        return {"sha256": out["sha256"], "key": self.table.entry_dirs[source].name}  # type: ignore

    def _job(self, task: Task, key: str, doc: dict, hashes: Any, force: bool) -> Job:
        records: dict[str, Any] = {}
        for b in task.bindings:
            if b.fan_in:
                records[b.name] = {"stage": b.producer, "items": {
                    self.table.item_ids[s]: self._provenance(s, b.name) for s in b.sources}}
            else:
                records[b.name] = {"stage": b.producer,
                                   **self._provenance(b.sources[0], b.name)}
        level = task.item.axes
        if level not in self._full_by_level:
            groups: dict[Item, list[Item]] = {}
            for full in self.wf.axes.all_items():
                groups.setdefault(full.project(level), []).append(full)
            self._full_by_level[level] = groups
        items = self._full_by_level[level].get(task.item, [])
        return Job(index=task.index, stage=task.stage, item=task.item, items=items,
                   params=task.params.value, params_json=task.params.json, key=key,
                   key_doc=doc, inputs=self.table.input_paths(task, self.task_items),
                   input_records=records, settings=self.wf.settings,
                   cache_root=os.fspath(self.cache.root), force=force,
                   package_version=self.options.package_version,
                   executor=self.executor.name, workflow=os.fspath(self.wf.path))

    def _finish(self, result: JobResult) -> None:
        job, gpus = self.jobs.pop(result.index)
        self.gpu_free += gpus
        task = self.plan.tasks[result.index]
        hashes = job.key_doc["inputs"]
        if result.status in ("ok", "cached"):
            self.table.set(result.index, result.outputs, Path(result.entry_dir))  # type: ignore
            self._write_ref(task, result.key, "ok", hashes)
            self._prechecks_after(result.index)
            state = "done" if result.status == "ok" else "cached"
            self.progress.line(task, state, result.wall_s if state == "done" else None,
                               result.note)
            self._settle(result.index, Outcome(state, result.wall_s, result.note, key=result.key))
        elif result.status == "failed":
            if result.disk_full and not self.summary.stopped:
                self.summary.stopped = disk_full_message(self.cache.root)
                print(f"cobgs run: {self.summary.stopped}; no new task is started", file=sys.stderr)
            self._write_ref(task, result.key, "failed", hashes)
            self.progress.line(task, "FAILED", result.wall_s, result.error)
            if result.log_path:
                self.progress.line(task, "", note=f"log: {result.log_path}", final=False)
            self._settle(result.index, Outcome("failed", result.wall_s, result.error,
                                               result.log_path, result.key))
        else:
            self.summary.interrupted = True
            self._settle(result.index, Outcome("interrupted", result.wall_s, key=result.key))

    def _prechecks_after(self, index: int) -> None:
        """Prechecks whose last input ``index`` just made: a refusal stops new tasks."""
        for i, waits in list(self.prechecks.items()):
            if index not in waits.values():
                continue
            if any(self.table.entry_dirs[s] is None for s in waits.values()):
                continue
            del self.prechecks[i]
            task = self.plan.tasks[i]
            inputs = {name: self.table.entry_dirs[s] / self.table.outputs[s][name]["path"]  # type: ignore
                      for name, s in waits.items()}
            for b in task.bindings:  # the inputs that were done when the run was planned
                if b.name in task.stage.precheck_inputs and not b.fan_in and b.name not in inputs \
                        and self.table.entry_dirs[b.sources[0]] is not None:
                    s = b.sources[0]
                    inputs[b.name] = self.table.entry_dirs[s] / self.table.outputs[s][b.name]["path"]  # type: ignore
            message = run_precheck(task, inputs)
            if message and not self.summary.stopped:
                self.summary.stopped = message
                print(f"cobgs run: {message}; no new task is started", file=sys.stderr)
                print(f"refused   {task.id}: {message}", file=self.stream, flush=True)

    def run(self, t0: float) -> RunSummary:
        try:
            while (self.ready or self.jobs) and not self.summary.interrupted:
                self.ready.sort()
                cap = self.executor.capacity()
                deferred = []
                while self.ready and (cap is None or len(self.jobs) < cap) and not self.summary.stopped:
                    index = self.ready.pop(0)
                    if not self._start(index):
                        deferred.append(index)
                self.ready = deferred + self.ready
                if self.jobs:
                    for result in self.executor.wait():
                        self._finish(result)
                elif self.summary.stopped:
                    break
        except KeyboardInterrupt:
            self.summary.interrupted = True
        if self.summary.interrupted and self.jobs:
            for result in self.executor.interrupt():
                if result.index in self.jobs:
                    self._finish(result)
            self.summary.interrupted = True
        self.summary.wall_s = time.perf_counter() - t0
        print_summary(self.summary, self.stream)
        return self.summary


def print_summary(summary: RunSummary, stream: TextIO) -> None:
    counts: dict[str, int] = {}
    for o in summary.outcomes.values():
        counts[o.state] = counts.get(o.state, 0) + 1
    order = ("done", "cached", "reused", "failed", "blocked", "unavailable", "interrupted")
    parts = [f"{counts[s]} {s}" for s in order if counts.get(s)]
    if summary.interrupted:
        # say what each number counts: an interrupted run settles only part of its tasks
        finished = sum(counts.get(s, 0) for s in ("done", "cached", "reused"))
        total = max(summary.total, len(summary.outcomes))
        stopped = counts.get("interrupted", 0)
        rest = ", ".join(f"{counts[s]} {s}" for s in ("done", "cached", "reused", "failed", "blocked",
                                                     "unavailable") if counts.get(s))
        print(f"interrupted: {finished} of {total} tasks finished ({rest or 'none'}); {stopped} running "
              f"or waiting on them were stopped, {total - len(summary.outcomes)} not started "
              f"({summary.wall_s:.2f} s)", file=stream)
    elif summary.stopped:
        print(f"run stopped: {summary.stopped}. {len(summary.outcomes)} of {summary.total} tasks settled "
              f"({', '.join(parts) or 'none'}), the rest not started ({summary.wall_s:.2f} s)", file=stream)
    else:
        print(f"run finished: {len(summary.outcomes)} tasks: {', '.join(parts) or 'nothing to do'} "
              f"({summary.wall_s:.2f} s)", file=stream)
    for task in summary.tasks_in("failed"):
        o = summary.outcomes[task.index]
        log = f"\n    log: {o.log_path}" if o.log_path else ""
        print(f"  FAILED  {task.id}: {o.note}{log}", file=stream)
    for task in summary.tasks_in("blocked", "unavailable"):
        print(f"  {summary.outcomes[task.index].state.upper():<8}{task.id}: "
              f"{summary.outcomes[task.index].note}", file=stream)
    if summary.interrupted:
        print("  interrupted: running tasks were discarded; finished ones are kept", file=stream)


def dry_run(plan: Plan, sel: Selection, cache: Cache, stream: TextIO, t0: float) -> RunSummary:
    """Print what a run would do and why, without running or writing anything."""
    states = inspect(plan, cache)
    will_run: set[int] = set()
    summary = RunSummary(plan)
    progress = Progress(plan, len(sel.relevant), stream, quiet=False)
    for note in sel.notes:
        print(note, file=stream)
    for i in sel.relevant:
        st, task = states[i], plan.tasks[i]
        upstream = [plan.tasks[d] for d in task.deps if d in will_run]
        if i not in sel.selected:
            if st.state == "done":
                outcome = Outcome("reused")
            else:
                outcome = Outcome("unavailable", note="not done, and not selected by "
                                                      "--only/--items: dependents will block")
                progress.line(task, "not done", note=outcome.note)
            summary.outcomes[i] = outcome
            continue
        if task.twin is not None and task.twin in will_run and i not in sel.forced:
            # keyed as its twin: the twin's run computes the one entry both use
            note = f"shared: {plan.tasks[task.twin].id} computes the one entry both use"
            progress.line(task, "shared", note=note)
            summary.outcomes[i] = Outcome("shared", note=note)
            continue
        if i in sel.forced:
            reasons = ["forced"]
        elif st.state == "done" and not upstream:
            progress.line(task, "cached", note=f"shared with {plan.tasks[task.twin].id}" if task.twin is not None
                          else "")
            summary.outcomes[i] = Outcome("cached")
            continue
        elif st.state == "done":
            reasons = [f"may rerun: upstream {upstream[0].id} will run"]
        else:
            reasons = [r for r in st.reasons if not r.startswith("waits on")]
            if upstream:
                reasons.append(f"upstream {upstream[0].id} will run")
            elif not reasons:
                reasons = [r for r in st.reasons] or ["new"]
        will_run.add(i)
        progress.line(task, "would run", note="; ".join(reasons))
        summary.outcomes[i] = Outcome("would run", note="; ".join(reasons))
    n = sum(1 for o in summary.outcomes.values() if o.state == "would run")
    shared = sum(1 for o in summary.outcomes.values() if o.state == "shared")
    print(f"dry run: {n} of {len(sel.relevant)} tasks would run"
          + (f" ({shared} more share their twin's entry)" if shared else "")
          + f"; nothing was executed (cache: {cache.root})", file=stream)
    summary.wall_s = time.perf_counter() - t0
    return summary
