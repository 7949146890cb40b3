"""Command-line plumbing for workflow commands: ``run``, ``status``, ``cache ...``,
``stages``. A program registers them with :func:`register`, giving a function that builds
its stage registry and its version string (the engine never imports the program).

Cache folder: ``--cache-dir``, else ``$COBGS_CACHE_DIR``, else ``./runs/cache`` (relative
to the current directory).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any, Callable, Optional, Sequence, TextIO

from .errors import PipelineError

from .cache import CACHE_ENV, DEFAULT_CACHE, default_cache_dir  # noqa: F401 (the commands' names for them)

RegistryFactory = Callable[[], Any]


def _fmt_time(ts: Optional[float]) -> str:
    return time.strftime("%Y-%m-%d %H:%M", time.localtime(ts)) if ts else ""


def _fmt_bytes(n: Optional[float]) -> str:
    if n is None:
        return ""
    for unit in ("B", "KiB", "MiB", "GiB"):
        if abs(n) < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return ""


def _guard(name: str, fn: Callable[[argparse.Namespace], int]) -> Callable[..., int]:
    def wrapped(args: argparse.Namespace) -> int:
        try:
            return fn(args)
        except PipelineError as exc:
            print(f"cobgs {name}: error: {exc}", file=sys.stderr)
            return 2
    return wrapped


def nonempty(what: str) -> Callable[[str], str]:
    """An argparse type: the text as given, refusing an empty or blank one (``--force ""`` from
    a script whose variable was unset would otherwise mean "nothing")."""
    def check(text: str) -> str:
        if not text.strip():
            raise argparse.ArgumentTypeError(f"it is empty; leave the option out, or give {what}")
        return text
    check.__name__ = what  # (argparse names the type in its messages)
    return check


CACHE_HELP = (f"cache folder (default: ${CACHE_ENV}, else ./{DEFAULT_CACHE} in the current directory)")


def add_cache_dir(parser: argparse.ArgumentParser) -> None:
    """``--cache-dir``, the same on every command that reads or writes a cache."""
    parser.add_argument("--cache-dir", type=nonempty("a folder"), metavar="DIR", help=CACHE_HELP)


SET_HELP = ("override: STAGE.PARAM=VALUE, device=cuda, or axes.AXIS.VALUE.KEY=VALUE (repeatable); commands that "
            "read a run's results take the same overrides the run used (they select its cache entries)")


def add_sets(parser: argparse.ArgumentParser) -> None:
    """``--set`` (into ``args.sets``), the same on every command that loads a workflow."""
    parser.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE", help=SET_HELP)


def _csv(text: Optional[str]) -> tuple[str, ...]:
    return tuple(s.strip() for s in (text or "").split(",") if s.strip())


def register(sub: Any, registry_factory: RegistryFactory, package_version: Callable[[], str]
             ) -> None:
    """Add ``run``, ``status``, ``cache`` and ``stages`` to an argparse sub-parser set."""

    p = sub.add_parser("run", help="run a workflow: compute what is missing or stale",
                       description="Run a workflow. Cached tasks are reused; the rest run "
                       "in dependency order. Exit code 1 names failed or blocked tasks.")
    p.add_argument("workflow", help="workflow TOML file")
    p.add_argument("--only", metavar="STAGES", type=nonempty("stage names"), help="run only these stages (comma list); "
                   "their upstream must already be done")
    p.add_argument("--from", dest="from_", metavar="STAGES", type=nonempty("stage names"),
                   help="recompute these stages and every stage downstream of them")
    p.add_argument("--items", metavar="ITEMS", type=nonempty("item patterns"), help="only these items: comma list of "
                   "patterns like lego, scene=lego, lego/no_*")
    p.add_argument("--force", metavar="STAGES", type=nonempty("stage names"), help="recompute these stages even if "
                   "cached (comma list, or 'all'); the external data they read are re-hashed, so an "
                   "edit that kept a file's size and time reruns every task that reads it")
    p.add_argument("--verify-data", action="store_true",
                   help="re-hash every external input (data, mask and model folders) instead of trusting "
                        "file sizes and times; what changed reruns")
    p.add_argument("--dry-run", action="store_true", help="print what would run and why")
    add_sets(p)
    p.add_argument("-j", "--jobs", type=int, default=1,
                   help="local executor: tasks at once, each in its own process (default 1: "
                        "in this process)")
    p.add_argument("--executor", choices=("local", "ray"), default="local")
    p.add_argument("--address", help="Ray cluster address (default: start a local instance)")
    add_cache_dir(p)
    p.add_argument("-q", "--quiet", action="store_true", help="no line for cached tasks")
    p.set_defaults(func=_guard("run", lambda a: cmd_run(a, registry_factory,
                                                         package_version())))

    p = sub.add_parser("status", help="show every item x stage of a workflow: done / stale "
                       "/ missing / failed, with timings")
    p.add_argument("workflow")
    add_sets(p)
    p.add_argument("--items", metavar="ITEMS", type=nonempty("item patterns"), help="only tasks of these items")
    p.add_argument("--logs", action="store_true", help="print the full log of each failure")
    p.add_argument("--verify-data", action="store_true",
                   help="re-hash every external input instead of trusting file sizes and times, and list "
                        "what would rerun (reads every byte of the data; writes nothing)")
    add_cache_dir(p)
    p.set_defaults(func=_guard("status", lambda a: cmd_status(a, registry_factory)))

    p = sub.add_parser("cache", help="inspect and clean the cache folder")
    csub = p.add_subparsers(dest="cache_command", metavar="SUBCOMMAND", required=True)
    q = csub.add_parser("gc", help="remove entries that none of the given workflows uses")
    q.add_argument("workflows", nargs="+", help="every workflow whose results to keep")
    add_sets(q)
    q.add_argument("--dry-run", action="store_true", help="list what would be removed")
    q.add_argument("--yes", action="store_true", help="do not ask (on a terminal, gc lists what it removes "
                   "and asks first; without a terminal, removing needs --yes)")
    add_cache_dir(q)
    q.set_defaults(func=_guard("cache gc", lambda a: cmd_gc(a, registry_factory)))
    q = csub.add_parser("ls", help="list cache entries")
    q.add_argument("--stage", help="only this stage")
    q.add_argument("--failed", action="store_true", help="list failure records instead")
    add_cache_dir(q)
    q.set_defaults(func=_guard("cache ls", cmd_ls))
    q = csub.add_parser("verify", help="re-hash every entry's outputs against its manifest")
    q.add_argument("--fix", action="store_true", help="remove entries that do not match")
    add_cache_dir(q)
    q.set_defaults(func=_guard("cache verify", cmd_verify))

    p = sub.add_parser("stages", help="list the registered stages (or their params as TOML)")
    p.add_argument("--toml", action="store_true",
                   help="print every stage's default params as a [params.STAGE] table, with each "
                   "value's valid range")
    p.add_argument("--docs", metavar="FILE", help="write that text into FILE between its generated-params "
                   "markers (docs/pipeline.md)")
    p.add_argument("--presets", action="store_true", help="list the presets an axis value may start from "
                   "(preset = \"NAME\"), with what each sets")
    p.set_defaults(func=_guard("stages", lambda a: cmd_stages(a, registry_factory)))


def cmd_run(args: argparse.Namespace, registry_factory: RegistryFactory,
            version: str, stream: Optional[TextIO] = None) -> int:
    stream = stream if stream is not None else sys.stdout
    from .run import RunOptions, run_workflow
    from .workflow import load_workflow

    wf = load_workflow(args.workflow, registry_factory(), args.sets)
    options = RunOptions(cache_dir=default_cache_dir(args.cache_dir), package_version=version,
                         executor=args.executor, jobs=args.jobs, address=args.address,
                         only=_csv(args.only), from_stages=_csv(args.from_),
                         force=_csv(args.force), items=args.items, dry_run=args.dry_run,
                         quiet=args.quiet, verify_data=args.verify_data)
    print(f"workflow {wf.name} ({wf.path}); cache {options.cache_dir.resolve()}; "
          f"device {wf.settings.device}; executor {options.executor}"
          + (f" x{options.jobs}" if options.executor == "local" and options.jobs > 1 else ""),
          file=stream, flush=True)
    summary = run_workflow(wf, options, stream)
    if summary.exit_code == 1:
        failed = [t.id for t in summary.tasks_in("failed", "blocked", "unavailable")]
        print(f"cobgs run: {len(failed)} task(s) not done: {', '.join(failed[:10])}"
              + (" ..." if len(failed) > 10 else ""), file=sys.stderr)
    return summary.exit_code


def cmd_status(args: argparse.Namespace, registry_factory: RegistryFactory,
               stream: Optional[TextIO] = None) -> int:
    stream = stream if stream is not None else sys.stdout
    from .api import entries
    from .items import ItemFilter
    from .workflow import load_workflow

    wf = load_workflow(args.workflow, registry_factory(), args.sets)
    cache_dir = default_cache_dir(args.cache_dir)
    verify = getattr(args, "verify_data", False)
    if verify:
        wf.verify_data()
    records = entries(wf, cache_dir)
    if args.items:
        filt = ItemFilter.parse(args.items, wf.axes)
        keep = {f for f in wf.axes.all_items() if filt.selects_full(f)}
        records = [r for r in records
                   if any(all(f.values.get(a) == v for a, v in r.item.pairs) for f in keep)]
    print(f"workflow {wf.name} ({wf.path}); cache {Path(cache_dir).resolve()}", file=stream)
    w_stage = max([len(r.stage) for r in records] + [5])
    w_item = min(max([len(r.item.label) for r in records] + [4]), 40)
    print(f"{'stage':<{w_stage}}  {'item':<{w_item}}  {'state':<8} {'wall':>9}  "
          f"{'finished':<16}  {'peak RSS':>9}  key / notes", file=stream)
    counts: dict[str, int] = {}
    for r in records:
        counts[r.state] = counts.get(r.state, 0) + 1
        m = r.manifest or {}
        wall = f"{m['wall_s']:.2f} s" if isinstance(m.get("wall_s"), (int, float)) else ""
        notes = (r.key or "")[:12]
        if r.reasons:
            notes += ("  " if notes else "") + "; ".join(r.reasons)
        print(f"{r.stage:<{w_stage}}  {r.item.label:<{w_item}}  {r.state:<8} {wall:>9}  "
              f"{_fmt_time(m.get('finished')):<16}  {_fmt_bytes(m.get('peak_rss_bytes')):>9}  "
              f"{notes}".rstrip(), file=stream)
    print(", ".join(f"{n} {s}" for s, n in sorted(counts.items())) or "no tasks", file=stream)
    if verify:
        changed = [r for r in records if any(x.startswith("data on disk changed") for x in r.reasons)]
        print(f"--verify-data: every external input re-hashed; {len(changed)} task(s) read data whose content "
              "changed" + (": " + ", ".join(r.task.id for r in changed[:12]) + (" ..." if len(changed) > 12 else "")
                           + f"; `cobgs run {args.workflow} --verify-data` reruns them and what depends on them"
                           if changed else ""), file=stream)
    for r in records:
        if r.state == "failed":
            print(f"FAILED {r.task.id}: {(r.manifest or {}).get('error', {}).get('summary')}\n"
                  f"  log: {r.log_path}", file=stream)
            if args.logs and r.log_path and r.log_path.exists():
                print(r.log_path.read_text(errors="replace"), file=stream)
    return 0


def referenced_keys(workflows: Sequence[str], registry: Any, sets: Sequence[str],
                    cache_dir: Path) -> set[tuple[str, str]]:
    """``(stage, key)`` a set of workflows references: every task key known under the
    current configuration (with ``sets``), plus the entry each task slot last produced
    (from ``refs/``), so stale results and results of earlier ``--set`` runs that are still
    a slot's latest survive until the slot runs again."""
    from .cache import Cache
    from .plan import Plan, inspect
    from .workflow import load_workflow

    cache = Cache(cache_dir)
    keep: set[tuple[str, str]] = set()
    for path in workflows:
        wf = load_workflow(path, registry, sets)
        for st in inspect(Plan(wf), cache, with_reasons=False):
            if st.key:
                keep.add((st.stage, st.key))
            ref = cache.read_ref(wf.id, st.stage, st.item.id)
            if ref is not None and ref.get("status") == "ok" and isinstance(ref.get("key"), str):
                keep.add((st.stage, ref["key"]))
    return keep


def _require_cache(cache_dir) -> None:
    """A cache command on a folder that is no cache (a typo) is an error, not "nothing to do"."""
    root = Path(cache_dir)
    if not (root / "entries").is_dir():
        why = "does not exist" if not root.exists() else "is not a cobgs cache (no entries/ folder)"
        raise PipelineError(f"cache folder {root} {why}")


def _prove_cache(cache_dir) -> None:
    """A deleting command's first step: the folder must prove it is a cache (pipeline.cache)."""
    from .cache import Cache
    from .errors import CacheError

    try:
        Cache(cache_dir).prove()
    except CacheError as exc:
        raise PipelineError(str(exc)) from None


def _foreign_lines(foreign: Sequence[str], stream: TextIO) -> None:
    for line in foreign[:10]:
        print(f"  left alone (not written by the cache): {line}", file=stream)
    if len(foreign) > 10:
        print(f"  left alone: {len(foreign) - 10} more", file=stream)


def cmd_gc(args: argparse.Namespace, registry_factory: RegistryFactory,
           stream: Optional[TextIO] = None) -> int:
    stream = stream if stream is not None else sys.stdout
    from .gc import collect, snapshot

    cache_dir = default_cache_dir(args.cache_dir)
    _require_cache(cache_dir)
    _prove_cache(cache_dir)
    existing = snapshot(cache_dir)  # entries committed from now on are kept (a run beside gc)
    keep = referenced_keys(args.workflows, registry_factory(), args.sets, cache_dir)
    if not args.dry_run and not getattr(args, "yes", False):
        # say what goes, and ask (a mistyped workflow would empty the cache); without a terminal to
        # ask on, removing needs --yes
        plan = collect(cache_dir, keep, dry_run=True, existing=existing)
        interactive = sys.stdin is not None and sys.stdin.isatty()
        if plan.removed and not interactive:
            raise PipelineError(f"cache gc would remove {plan.removed} entries/records ({_fmt_bytes(plan.bytes)}) "
                                f"from {Path(cache_dir).resolve()}; with no terminal to ask on, pass --yes to remove "
                                "them, or --dry-run to list them")
        if plan.removed:
            for line in plan.lines:
                print(f"  would remove {line}", file=stream)
            total = plan.removed + plan.kept
            print(f"cache gc: remove {plan.removed} of {total} entries/records ({_fmt_bytes(plan.bytes)}) "
                  f"that {len(args.workflows)} workflow(s) do not use? [y/N] ", end="", file=stream, flush=True)
            if input().strip().lower() not in ("y", "yes"):
                print("cache gc: nothing removed", file=stream)
                return 1
    report = collect(cache_dir, keep, dry_run=args.dry_run, existing=existing)
    verb = "would remove" if args.dry_run else "removed"
    for line in report.lines:
        print(f"  {verb} {line}", file=stream)
    _foreign_lines(report.foreign, stream)
    print(f"cache gc: kept {report.kept} entries referenced by {len(args.workflows)} "
          f"workflow(s); {verb} {report.removed} entries/records "
          f"({_fmt_bytes(report.bytes)}) in {Path(cache_dir).resolve()}"
          + (f"; left {len(report.foreign)} item(s) the cache did not write" if report.foreign else ""),
          file=stream)
    return 0


def cmd_ls(args: argparse.Namespace, stream: Optional[TextIO] = None) -> int:
    stream = stream if stream is not None else sys.stdout
    from .cache import MANIFEST, Cache, manifest_problem, read_json_object

    _require_cache(default_cache_dir(args.cache_dir))
    cache = Cache(default_cache_dir(args.cache_dir))
    n = 0
    print(f"{'stage':<12} {'key':<12}  {'item':<24} {'status':<7} {'size':>10} {'wall':>10}  finished",
          file=stream)
    for stage, key, folder in cache.iter_entries("failed" if args.failed else "entries"):
        if args.stage and stage != args.stage:
            continue
        m = read_json_object(folder / MANIFEST)
        if m is None or (not args.failed and manifest_problem(m, folder)) \
                or not isinstance(m.get("item") or {}, dict):
            m = {"status": "corrupt"}
        outs = m.get("outputs") if isinstance(m.get("outputs"), dict) else {}
        size = sum(o.get("bytes", 0) for o in outs.values()
                   if isinstance(o, dict) and isinstance(o.get("bytes", 0), int))
        wall = m.get("wall_s")
        print(f"{stage:<12} {key[:12]}  {(m.get('item') or {}).get('id') or '(workflow)':<24} "
              f"{m.get('status', '?'):<7} {_fmt_bytes(size):>10} "
              f"{(f'{wall:.2f} s' if isinstance(wall, (int, float)) else ''):>10}  "
              f"{_fmt_time(m.get('finished'))}", file=stream)
        n += 1
    print(f"{n} {'failure records' if args.failed else 'entries'} in {cache.root}", file=stream)
    return 0


def cmd_verify(args: argparse.Namespace, stream: Optional[TextIO] = None) -> int:
    stream = stream if stream is not None else sys.stdout
    from .cache import MANIFEST, Cache, entry_shape_problem, manifest_problem, read_json
    from .hashing import tree_hash

    _require_cache(default_cache_dir(args.cache_dir))
    if args.fix:
        _prove_cache(default_cache_dir(args.cache_dir))
    cache = Cache(default_cache_dir(args.cache_dir))
    bad = total = 0
    foreign: list[str] = []
    for stage, key, folder in cache.iter_entries():
        why = entry_shape_problem(stage, key, folder)
        if why:  # not something the cache wrote: never an entry, never removed
            foreign.append(f"entries/{stage}/{key} ({why})")
            continue
        total += 1
        problem = ""
        try:
            m = read_json(folder / MANIFEST)
            why = manifest_problem(m, folder)
            if why:
                raise ValueError(f"the manifest is malformed: {why}")
            for name, out in m["outputs"].items():
                if tree_hash(folder / out["path"]).sha256 != out["sha256"]:
                    problem = f"output {name!r} does not match its recorded hash"
                    break
        except (OSError, ValueError, KeyError, TypeError) as exc:
            problem = f"unreadable: {exc}"
        if problem:
            bad += 1
            print(f"  {stage} {key[:12]}: {problem}" + (" (removed)" if args.fix else ""),
                  file=stream)
            if args.fix:
                cache.remove_entry(stage, key)
    _foreign_lines(foreign, stream)
    print(f"cache verify: {total - bad} of {total} entries match their manifests"
          + (f"; {len(foreign)} item(s) under entries/ are not cache entries (left alone)" if foreign else ""),
          file=stream)
    return 1 if bad and not args.fix else 0


DOCS_BEGIN = "<!-- BEGIN GENERATED PARAMS (cobgs stages --toml) -->"
DOCS_END = "<!-- END GENERATED PARAMS -->"


def stages_toml(registry) -> str:
    """Every stage's default params as ``[params.STAGE]`` tables, each value's valid range
    beside it (what ``cobgs stages --toml`` prints)."""
    from .params import defaults_toml

    graph = registry.graph()
    return "".join(defaults_toml(graph.stages[n].params, f"params.{n}") + "\n\n" for n in graph.order)


def write_between(path: Path, begin: str, end: str, body: str, what: str) -> None:
    """Replace what lies between the markers ``begin`` ... ``end`` of an existing text file with
    ``body``, through a rename (never half-written). A file that cannot be read or lacks either
    marker is refused, naming it: only a section the writer marked is ever replaced. ``what``
    names the option that gave the path."""
    try:
        doc = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise PipelineError(f"{path}: cannot read it ({type(e).__name__}: {e}); {what} takes an existing "
                            f"Markdown file holding the {begin} ... {end} markers") from None
    if begin not in doc or end not in doc:
        raise PipelineError(f"{path}: no {begin} ... {end} markers to write between")
    head, rest = doc.split(begin, 1)
    _, tail = rest.split(end, 1)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_text(f"{head}{begin}{body}{end}{tail}", encoding="utf-8")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_params_docs(path: Path, text: str) -> int:
    """Put ``text`` between the generated-params markers of a Markdown file (a ```toml block);
    returns the number of tables written."""
    write_between(path, DOCS_BEGIN, DOCS_END, f"\n```toml\n{text.rstrip()}\n```\n", "--docs")
    return text.count("[params.")


def cmd_stages(args: argparse.Namespace, registry_factory: RegistryFactory,
               stream: Optional[TextIO] = None) -> int:
    stream = stream if stream is not None else sys.stdout
    registry = registry_factory()
    graph = registry.graph()
    if not graph.order:
        print("no stages are registered", file=stream)
        return 0
    if getattr(args, "presets", False):
        from .hashing import canonical_json

        for axis, presets in sorted(getattr(registry, "presets", {}).items()):
            for name, table in presets.items():
                print(f"{axis}.{name}: {canonical_json(table) if table else '(nothing: the defaults)'}", file=stream)
        return 0
    if getattr(args, "docs", None):
        n = write_params_docs(Path(args.docs), stages_toml(registry))
        print(f"wrote {n} params tables into {args.docs}", file=stream)
        return 0
    if args.toml:
        print(stages_toml(registry), file=stream, end="")
        return 0
    for name in graph.order:
        s = graph.stages[name]
        level = " x ".join(s.level) or "workflow"
        print(f"{name} v{s.version}  per {level}  {list(s.inputs)} -> {list(s.outputs)}"
              f"{'  (uses device)' if s.uses_device else ''}"
              + (f"\n    {s.description}" if s.description else ""), file=stream)
    return 0
