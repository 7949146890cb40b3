"""Engine overhead of the pipeline (issue 6 targets), on a no-op workflow.

    .venv/bin/python tests/benchmarks/bm_pipeline.py [--items 1000] [--big-mb 64]

Measures, on ITEMS items x 2 per-item stages + 1 fan-in stage of no-op work:
  * first run (everything computed, in process): engine cost per computed task
    (lock, temp folder, log, hashing, manifest with fsync, rename);
  * planning + cache verification (load the workflow, expand the plan, check every entry,
    as `cobgs status` / the first phase of a cached run do); target: < 5 s for 1,000 items;
  * a fully cached `run`: per cached item x stage overhead; target: < 5 ms;
  * hashing a large output once at commit time, and that checking an entry with a large
    output does not re-read it.
"""

from __future__ import annotations

import argparse
import io
import os
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from pipeline import Cache, Registry, RunOptions, Stage, load_workflow, run_workflow  # noqa
from pipeline.hashing import tree_hash  # noqa: E402
from pipeline.plan import Plan, inspect  # noqa: E402


@dataclass(frozen=True)
class P:
    scale: int = 1


def first(ctx, inputs):
    out = ctx.out_dir / "a.txt"
    out.write_text(f"{ctx.item.id} {ctx.params.scale}\n")
    return {"a": out}


def second(ctx, inputs):
    out = ctx.out_dir / "b.txt"
    out.write_text(Path(inputs["a"]).read_text() * 2)
    return {"b": out}


def gather(ctx, inputs):
    out = ctx.out_dir / "summary.txt"
    out.write_text(f"{len(inputs['b'])} items\n")
    return {"summary": out}


REGISTRY = Registry([
    Stage(name="first", version=1, run=first, outputs=("a",), params=P, level=("item",)),
    Stage(name="second", version=1, run=second, inputs=("a",), outputs=("b",),
          level=("item",)),
    Stage(name="gather", version=1, run=gather, inputs=("b",), outputs=("summary",)),
])


def write_workflow(folder: Path, n: int) -> Path:
    lines = ["[workflow]", 'name = "bench"', "", "[params.first]", "scale = 2", ""]
    for i in range(n):
        lines += [f"[axes.item.i{i:05d}]", f'group = "{i % 7}"', ""]
    path = folder / "bench.toml"
    path.write_text("\n".join(lines))
    return path


def timed(fn, repeat: int = 1):
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return result, times


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--items", type=int, default=1000)
    ap.add_argument("--big-mb", type=int, default=64)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    n = args.items
    with tempfile.TemporaryDirectory(dir=os.environ.get("BM_TMP")) as tmp:
        folder = Path(tmp)
        wf_path = write_workflow(folder, n)
        cache_dir = folder / "cache"
        sink = io.StringIO()

        wf = load_workflow(wf_path, REGISTRY)
        tasks = len(Plan(wf).tasks)
        summary, (t_first,) = timed(lambda: run_workflow(
            wf, RunOptions(cache_dir=cache_dir, quiet=True), stream=sink))
        assert summary.exit_code == 0, sink.getvalue()[-2000:]
        print(f"workflow: {n} items x 2 stages + 1 fan-in = {tasks} tasks")
        print(f"first run (all computed, in process): {t_first:.2f} s = "
              f"{1000 * t_first / tasks:.2f} ms per task")

        def plan_and_verify():
            wf = load_workflow(wf_path, REGISTRY)
            states = inspect(Plan(wf), Cache(cache_dir), with_reasons=False)
            assert all(s.state == "done" for s in states)
            return states
        _, t_plan = timed(plan_and_verify, args.repeat)
        best = min(t_plan)
        print(f"plan + verify cache ({tasks} tasks): best {best:.3f} s, median "
              f"{statistics.median(t_plan):.3f} s; target < 5 s: "
              f"{'met' if best < 5 else 'NOT met'} ({best / 5:.3f} of the budget)")

        def cached_run():
            wf = load_workflow(wf_path, REGISTRY)
            s = run_workflow(wf, RunOptions(cache_dir=cache_dir, quiet=True), stream=sink)
            assert s.exit_code == 0 and all(o.state == "cached" for o in s.outcomes.values())
        _, t_run = timed(cached_run, args.repeat)
        per = 1000 * min(t_run) / tasks
        print(f"fully cached run: best {min(t_run):.3f} s = {per:.3f} ms per item x stage "
              f"(load + plan + check + progress); target < 5 ms: "
              f"{'met' if per < 5 else 'NOT met'} ({per / 5:.3f} of the budget)")

        big = folder / "big.bin"
        with open(big, "wb") as f:
            for _ in range(args.big_mb):
                f.write(os.urandom(1 << 20))
        h, (t_hash,) = timed(lambda: tree_hash(big))
        print(f"hash at commit: {args.big_mb} MiB in {t_hash:.3f} s = "
              f"{args.big_mb / t_hash:.0f} MiB/s (once per entry, stored in the manifest)")

        def stage_big(ctx, inputs):
            out = ctx.out_dir / "big.bin"
            os.link(big, out)  # the content is what matters, not how it got there
            return {"big": out}
        reg = Registry([Stage(name="big", version=1, run=stage_big, outputs=("big",))])
        (folder / "one.toml").write_text("")
        one = load_workflow(folder / "one.toml", reg)
        run_workflow(one, RunOptions(cache_dir=cache_dir), stream=sink)
        cache = Cache(cache_dir)
        (st,) = inspect(Plan(one), cache, with_reasons=False)
        small = inspect(Plan(wf), cache, with_reasons=False)[0]
        _, t_big = timed(lambda: cache.check("big", st.key), 200)
        _, t_small = timed(lambda: cache.check(small.stage, small.key), 200)
        print(f"cached check of an entry: {args.big_mb} MiB output "
              f"{1e6 * statistics.median(t_big):.0f} us vs tiny output "
              f"{1e6 * statistics.median(t_small):.0f} us (ratio "
              f"{statistics.median(t_big) / statistics.median(t_small):.2f}: no re-hash)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
