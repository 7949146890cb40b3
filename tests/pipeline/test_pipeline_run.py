"""Running workflows in-process: order, caching, invalidation, reruns, failures, API."""

from __future__ import annotations

import io
import json
import shutil
import sys
from dataclasses import dataclass

import pytest

import pipeline_toys as toys
from pipeline import (MissingInputError, Registry, RunOptions, Stage, WorkflowError, entries,
                      entry_of, load_manifest, load_workflow, run_workflow, upstream_entries)
from pipeline.cache import Cache
from pipeline.commands import referenced_keys
from pipeline.gc import collect
from pipeline.hashing import tree_hash

ALL = {"load": 2, "train": 2, "refine": 4, "evaluate": 4, "summary": 1}


def states(toy, sets=(), registry=None):
    return {(r.stage, r.item.id): r for r in entries(toy.load(sets, registry), toy.cache)}


def test_first_run_orders_fans_out_and_gathers(toy, executions):
    summary = toy.run()
    assert summary.exit_code == 0, summary.output
    assert executions.stages() == ALL
    lines = executions.lines()
    for scene in ("alpha", "beta"):
        assert lines.index(f"load {scene}") < lines.index(f"train {scene}")
        for method in ("full", "nosplit"):
            item = f"{scene}/{method}"
            assert lines.index(f"train {scene}") < lines.index(f"refine {item}") \
                < lines.index(f"evaluate {item}") < lines.index("summary ")
    recs = states(toy)
    assert {r.state for r in recs.values()} == {"done"}
    out = json.loads(recs[("summary", "")].output("summary").read_text())
    assert sorted(out["rows"]) == ["alpha/full", "alpha/nosplit", "beta/full", "beta/nosplit"]
    assert out["items"] == ["alpha/full", "alpha/nosplit", "beta/full", "beta/nosplit"]
    gathered = upstream_entries(recs[("summary", "")].entry_dir)["metrics"]
    assert gathered == {i: recs[("evaluate", i)].entry_dir for i in out["items"]}
    # Each refine read its own scene's model: per-item params flowed through.
    text = recs[("refine", "beta/nosplit")].output("refined").read_text()
    assert "scene=beta" in text and "iterations=20" in text and "split=False" in text
    assert "scene=alpha" in recs[("refine", "alpha/full")].output("refined").read_text()
    assert "[ 1/13] load" in summary.output and "13 done" in summary.output


def test_manifest_records_the_run(toy):
    toy.run()
    rec = states(toy)[("train", "beta")]
    m = rec.manifest
    assert m["key"] == rec.key and m["status"] == "ok" and m["stage"] == "train"
    assert m["version"] == 1 and m["params"] == {"iterations": 20, "fail_on": "", "disk_full_on": ""}
    assert m["item"]["id"] == "beta" and m["item"]["values"] == {"scene": "beta"}
    assert m["item"]["attrs"] == {"scene": {"kind": "synthetic"}}
    upstream = states(toy)[("load", "beta")]
    assert m["inputs"]["data"] == {"stage": "load", "key": upstream.key,
                                   "sha256": upstream.manifest["outputs"]["data"]["sha256"]}
    assert m["device"] == "cpu" and m["package_version"] == "t" and m["host"]
    # The distributions the task process had imported, with their versions (pytest is
    # imported in this process; the standard library is not a distribution).
    from importlib import metadata
    assert m["dependencies"].get("pytest") == metadata.version("pytest")
    assert "os" not in m["dependencies"] and "json" not in m["dependencies"]
    assert m["started"] <= m["finished"] and m["wall_s"] >= 0 and m["cpu_s"] >= 0
    assert m["peak_rss_bytes"] > 1 << 20 and m["peak_rss_scope"] == "task"
    assert m["extra"] == {"iterations_done": 20}
    out = m["outputs"]["model"]
    assert out["kind"] == "dir" and out["files"] == 2 and out["bytes"] > 1024
    assert out["sha256"] == tree_hash(rec.output("model")).sha256
    log = rec.log_path.read_text()
    assert "trained beta" in log and rec.key in log


def test_second_run_is_a_full_cache_hit(toy, executions):
    toy.run()
    executions.reset()
    summary = toy.run()
    assert executions.lines() == [] and summary.exit_code == 0
    assert "13 cached" in summary.output


def test_params_change_reruns_that_stage_and_what_its_output_changes(toy, executions):
    toy.run()
    executions.reset()
    toy.run(sets=["refine.strength=2"])
    # evaluate's input changed; its metrics (a length) did not, so summary stays cached.
    assert executions.stages() == {"refine": 4, "evaluate": 4}
    executions.reset()
    toy.run(sets=["axes.method.full.refine.strength=3"])  # only the 'full' method's rows
    assert executions.count() == {"refine alpha/full": 1, "refine beta/full": 1,
                                  "evaluate alpha/full": 1, "evaluate beta/full": 1}


def test_key_params_leave_unread_params_out_of_the_key(toy, executions):
    """A stage declaring key_params: a change to a param its tasks do not read (here
    ``sleep_s``, and ``strength`` when not splitting) recomputes nothing; one they read does;
    --dry-run names the read param that changed."""
    from dataclasses import replace

    def key(params, full):
        return {k: v for k, v in full.items() if k == "split" or (k == "strength" and params.split)}

    reg = Registry([replace(s, key_params=key) if s.name == "refine" else s for s in toys.STAGES])
    toy.run(registry=reg)
    executions.reset()
    toy.run(sets=["refine.sleep_s=0.001"], registry=reg)
    assert executions.count() == {}
    toy.run(sets=["axes.method.nosplit.refine.strength=7"], registry=reg)  # nosplit does not read it
    assert executions.count() == {}
    toy.run(sets=["refine.strength=2"], registry=reg)  # the 'full' rows read it
    assert executions.count() == {"refine alpha/full": 1, "refine beta/full": 1,
                                  "evaluate alpha/full": 1, "evaluate beta/full": 1}
    out = io.StringIO()
    run_workflow(toy.load(["refine.strength=3"], reg), RunOptions(cache_dir=toy.cache, dry_run=True), stream=out)
    assert "params changed (strength" in out.getvalue() and "sleep_s" not in out.getvalue()
    # the manifest still records every param
    man = next(m for m in (json.loads(f.read_text()) for f in (toy.cache / "entries" / "refine").glob("*/manifest.json")))
    assert "sleep_s" in man["params"]
    with pytest.raises(Exception, match="key_params must be callable"):
        replace(toys.STAGES[2], key_params=3)


def test_upstream_content_change_propagates(toy, executions):
    toy.run()
    executions.reset()
    toy.run(sets=["load.size=5"])
    assert executions.stages() == {k: v for k, v in ALL.items() if k != "summary"}


def test_version_bump_reruns_the_stage(toy, executions):
    toy.run()
    executions.reset()
    toy.run(registry=toys.registry(refine=2))
    # refine reruns; its output bytes are unchanged, so evaluate's key is too.
    assert executions.stages() == {"refine": 4}
    executions.reset()
    toy.run(registry=toys.registry(load="2b", evaluate=3))
    assert executions.stages() == {"load": 2, "evaluate": 4}


def test_device_enters_keys_of_device_stages_only(toy, executions):
    toy.run()
    executions.reset()
    toy.run(sets=["device=cuda"])
    # load does not use the device; train does and writes it into its output, which
    # changes every later output (the metrics hold the text length: "cuda" vs "cpu").
    assert executions.stages() == {"train": 2, "refine": 4, "evaluate": 4, "summary": 1}


def test_dry_run_gives_reasons_and_runs_nothing(toy, executions):
    summary = toy.run(dry_run=True)
    assert "new" in summary.output and "13 of 13 tasks would run" in summary.output
    assert executions.lines() == [] and not (toy.cache / "entries").exists()
    toy.run()
    out = toy.run(sets=["refine.strength=2"], dry_run=True).output
    assert "refine    alpha/full     would run" in out
    assert "params changed (strength: 1.0 -> 2.0)" in out
    assert "upstream refine[alpha/full] will run" in out
    assert "load      alpha          cached" in out
    out = toy.run(registry=toys.registry(evaluate=7), dry_run=True).output
    assert "version changed (1 -> 7)" in out and "evaluate  beta/full" in out
    # input changed: load reran with new params, train has not run on it yet.
    toy.run(sets=["load.size=9"], only=("load",))
    out = toy.run(sets=["load.size=9"], dry_run=True).output
    assert "train     alpha          would run               input changed (data)" in out
    out = toy.run(force=("train",), dry_run=True).output
    assert "train     beta           would run               forced" in out
    assert "may rerun: upstream train[alpha] will run" in out
    assert executions.stages() == {**ALL, "load": 4}


def test_failing_item_does_not_stop_the_others(toy, executions):
    summary = toy.run(sets=["train.fail_on=beta"])
    assert summary.exit_code == 1
    assert executions.stages() == {"load": 2, "train": 2, "refine": 2, "evaluate": 2}
    assert [t.id for t in summary.tasks_in("failed")] == ["train[beta]"]
    blocked = {t.id for t in summary.tasks_in("blocked")}
    assert blocked == {"refine[beta/full]", "refine[beta/nosplit]", "evaluate[beta/full]",
                       "evaluate[beta/nosplit]", "summary[(workflow)]"}
    assert "FAILED  train[beta]: RuntimeError: toy training diverged on beta" in summary.output
    rec = states(toy, ["train.fail_on=beta"])[("train", "beta")]
    assert rec.state == "failed"
    assert rec.manifest["error"]["type"] == "RuntimeError"
    log = rec.log_path.read_text()
    assert str(rec.log_path) in summary.output
    assert "Traceback" in log and "toy training diverged" in log
    assert not (toy.cache / "entries" / "train" / rec.key).exists()
    assert list((toy.cache / "tmp").iterdir()) == []
    # A later run retries the failure; fixing it clears the failure record.
    executions.reset()
    assert toy.run(sets=["train.fail_on=beta"]).exit_code == 1
    assert executions.stages() == {"train": 1}
    assert toy.run().exit_code == 0


@dataclass(frozen=True)
class BadParams:
    mode: str = "missing"


def run_bad(ctx, inputs):
    (ctx.out_dir / "partial.bin").write_bytes(b"x" * 100)
    if ctx.params.mode == "missing":
        return {}
    if ctx.params.mode == "outside":
        return {"thing": ctx.scratch_dir / ".." / ".." / "elsewhere"}
    if ctx.params.mode == "notexist":
        return {"thing": "nothere.txt"}
    return {"thing": "partial.bin", "other": "partial.bin"}


@pytest.mark.parametrize("mode, message", [
    ("missing", "returned outputs [], declared ['thing']"),
    ("outside", "does not exist"),
    ("notexist", "output 'thing' was returned as"),
    ("extra", "undeclared ['other']"),
])
def test_bad_outputs_fail_the_task_and_leave_nothing(tmp_path, mode, message):
    reg = Registry([Stage(name="bad", version=1, run=run_bad, outputs=("thing",),
                          params=BadParams)])
    wf_path = tmp_path / "wf.toml"
    wf_path.write_text(f"[params.bad]\nmode = '{mode}'\n")
    out = io.StringIO()
    summary = run_workflow(load_workflow(wf_path, reg), RunOptions(cache_dir=tmp_path / "c"),
                           stream=out)
    assert summary.exit_code == 1 and message in out.getvalue()
    assert not any((tmp_path / "c" / "entries").rglob("*"))
    assert list((tmp_path / "c" / "tmp").iterdir()) == []


def test_output_outside_the_entry_is_rejected(tmp_path):
    def run(ctx, inputs):
        target = tmp_path / "outside.txt"
        target.write_text("x")
        return {"thing": target}
    (tmp_path / "wf.toml").write_text("")
    out = io.StringIO()
    reg = Registry([Stage(name="leaky", version=1, run=run, outputs=("thing",))])
    summary = run_workflow(load_workflow(tmp_path / "wf.toml", reg),
                           RunOptions(cache_dir=tmp_path / "c"), stream=out)
    assert summary.exit_code == 1 and "is outside ctx.out_dir" in out.getvalue()


def test_only_from_force_and_items(toy, executions):
    s = toy.run(only=("evaluate",))  # nothing upstream is done: blocked, nothing runs
    assert s.exit_code == 1 and executions.lines() == []
    assert "not done, and not selected" in s.output
    assert "BLOCKED evaluate[alpha/full]: upstream load[alpha] is not done" in s.output
    toy.run()
    executions.reset()
    toy.run(only=("refine",), force=("refine",))
    assert executions.stages() == {"refine": 4}
    executions.reset()
    toy.run(from_stages=("refine",))
    assert executions.stages() == {"refine": 4, "evaluate": 4, "summary": 1}
    executions.reset()
    toy.run(force=("all",), items="alpha")
    assert executions.stages() == {"load": 1, "train": 1, "refine": 2, "evaluate": 2}
    executions.reset()
    s = toy.run(force=("all",), items="method=nosplit")
    assert executions.stages() == {"load": 2, "train": 2, "refine": 2, "evaluate": 2}
    assert "summary[(workflow)] skipped: it gathers items that --items leaves out" in s.output
    executions.reset()
    toy.run(force=("refine",), items="beta/n*,alpha/full")
    assert executions.count() == {"refine beta/nosplit": 1, "refine alpha/full": 1}
    with pytest.raises(WorkflowError, match="gamma matches no item"):
        toy.run(items="gamma")
    with pytest.raises(MissingInputError, match="--only: unknown stage 'refin'"):
        toy.run(only=("refin",))


def test_corrupt_entries_are_reported_and_recomputed(toy, executions, capsys):
    toy.run()
    recs = states(toy)
    (recs[("train", "alpha")].output("model") / "weights.txt").unlink()
    recs[("evaluate", "beta/full")].output("metrics").write_text("{}")  # size changed
    recs = states(toy)
    assert recs[("train", "alpha")].state == "corrupt"
    assert "output 'model': weights.txt is missing" in recs[("train", "alpha")].reasons[0]
    assert recs[("evaluate", "beta/full")].state == "corrupt"
    # Downstream of a corrupt entry the key is unknown until it is recomputed.
    assert recs[("refine", "alpha/full")].state == "stale"
    executions.reset()
    s = toy.run()
    assert s.exit_code == 0
    # Recomputed outputs are byte-identical, so nothing downstream of them reruns.
    assert executions.count() == {"train alpha": 1, "evaluate beta/full": 1}
    assert "corrupt entry" in s.output and "recomputing" in capsys.readouterr().err

    manifest = recs[("load", "beta")].entry_dir / "manifest.json"
    manifest.write_text(manifest.read_text()[:50])  # truncated
    assert states(toy)[("load", "beta")].state == "corrupt"
    shutil.rmtree(recs[("load", "alpha")].entry_dir / "out")
    (recs[("load", "alpha")].entry_dir / "manifest.json").unlink()  # a folder, no manifest
    assert "folder without manifest" in states(toy)[("load", "alpha")].reasons[0]
    executions.reset()
    assert toy.run().exit_code == 0
    assert executions.count() == {"load beta": 1, "load alpha": 1}
    assert {r.state for r in states(toy).values()} == {"done"}


def test_process_pool_matches_inline_and_records_failures(toy, executions):
    s = toy.run(jobs=2, sets=["train.fail_on=alpha"])
    assert s.exit_code == 1 and [t.id for t in s.tasks_in("failed")] == ["train[alpha]"]
    assert executions.stages() == {"load": 2, "train": 2, "refine": 2, "evaluate": 2}
    rec = states(toy, ["train.fail_on=alpha"])[("train", "alpha")]
    assert rec.state == "failed" and "diverged" in rec.log_path.read_text()
    assert rec.manifest["executor"] == "local-pool"
    executions.reset()
    assert toy.run(jobs=2).exit_code == 0
    executions.reset()
    assert toy.run().exit_code == 0 and executions.lines() == []  # same keys as inline


def test_peak_memory_is_per_task(tmp_path):
    def big(ctx, inputs):
        block = bytearray(96 << 20)
        block[:: 4096] = b"x" * len(block[:: 4096])  # touch every page
        (ctx.out_dir / "a").write_text("a")
        return {"a": ctx.out_dir / "a"}

    def small(ctx, inputs):
        (ctx.out_dir / "b").write_text("b")
        return {"b": ctx.out_dir / "b"}

    reg = Registry([Stage(name="big", version=1, run=big, outputs=("a",)),
                    Stage(name="small", version=1, run=small, inputs=("a",), outputs=("b",))])
    (tmp_path / "wf.toml").write_text("")
    wf = load_workflow(tmp_path / "wf.toml", reg)
    run_workflow(wf, RunOptions(cache_dir=tmp_path / "c"), stream=io.StringIO())
    recs = {r.stage: r.manifest for r in entries(wf, tmp_path / "c")}
    assert recs["big"]["peak_rss_bytes"] >= 96 << 20
    # The same process ran 'small' next: its peak must not include big's 96 MiB.
    assert recs["small"]["peak_rss_bytes"] < recs["big"]["peak_rss_bytes"] - (64 << 20)


def test_gc_keeps_what_workflows_reference(toy, executions):
    toy.run(sets=["refine.strength=2"])
    strength2 = {(r.stage, r.key) for r in entries(toy.load(["refine.strength=2"]), toy.cache)
                 if r.stage == "refine"}
    toy.run()
    toy.run(sets=["device=cuda"])
    toy.run(sets=["train.fail_on=beta"])
    fail_on = {(r.stage, r.item.id): r.key for r in entries(toy.load(["train.fail_on=beta"]),
                                                             toy.cache)}
    cache = Cache(toy.cache)
    before = {(s, k) for s, k, _ in cache.iter_entries()}
    keep = referenced_keys([str(toy.path)], toys.registry(), [], toy.cache)
    assert strength2 <= before and not strength2 & keep  # no slot's latest any more
    collect(toy.cache, keep, dry_run=True)
    assert {(s, k) for s, k, _ in cache.iter_entries()} == before  # dry run: untouched
    report = collect(toy.cache, keep)
    after = {(s, k) for s, k, _ in cache.iter_entries()}
    assert after == before & keep and not strength2 & after
    assert report.removed == len(before - after) + 1  # + train[beta]'s failure record
    assert list(cache.iter_entries("failed")) == []
    # The latest run of a slot survives even though the workflow's own params differ.
    assert ("train", fail_on[("train", "alpha")]) in after
    executions.reset()
    assert toy.run().exit_code == 0 and executions.lines() == []  # default: all cached
    assert toy.run(sets=["device=cuda"]).exit_code == 0
    # refine[beta/*] last ran on cuda (the fail_on run blocked them): kept and reused.
    assert "refine beta/full" not in executions.count()


def test_gc_keeps_an_entry_a_run_saves_while_it_decides(toy, executions):
    """gc works out what to keep, then scans; entries a concurrent run commits in between
    (their keys unknown to gc: they depend on outputs that did not exist yet) are kept, and
    the run finds them afterwards."""
    from pipeline.gc import snapshot

    existing = snapshot(toy.cache)
    keep = referenced_keys([str(toy.path)], toys.registry(), [], toy.cache)  # on an empty cache
    assert toy.run().exit_code == 0  # the run beside gc saves every entry
    saved = {(r.stage, r.key) for r in entries(toy.load(), toy.cache)}
    assert saved - keep  # downstream keys gc could not know
    collect(toy.cache, keep, existing=existing)
    assert saved <= {(s, k) for s, k, _ in Cache(toy.cache).iter_entries()}
    executions.reset()
    assert toy.run().exit_code == 0 and executions.lines() == []


def test_read_api_for_reports(toy):
    toy.run(sets=["train.fail_on=beta"])
    recs = entries(toy.load(["train.fail_on=beta"]), toy.cache)
    by = {(r.stage, r.item.id): r for r in recs}
    assert [r.stage for r in recs][:4] == ["load", "load", "train", "train"]
    assert by[("evaluate", "alpha/full")].state == "done"
    assert load_manifest(by[("evaluate", "alpha/full")].entry_dir)["stage"] == "evaluate"
    assert by[("train", "beta")].state == "failed"
    assert by[("refine", "beta/full")].state == "missing"
    assert by[("refine", "beta/full")].reasons == ["waits on train[beta]"]
    with pytest.raises(KeyError, match="is missing"):
        by[("refine", "beta/full")].output("refined")
    # Provenance from an artifact path, as a report stage would walk it.
    ev = by[("evaluate", "alpha/full")]
    assert entry_of(ev.output("metrics")) == ev.entry_dir
    assert upstream_entries(ev.entry_dir) == {"refined": by[("refine", "alpha/full")].entry_dir}
    with pytest.raises(FileNotFoundError, match="not inside a pipeline cache entry"):
        entry_of(toy.path)
    # Stale: this slot ran before with other params.
    recs = {(r.stage, r.item.id): r for r in entries(
        toy.load(["train.fail_on=beta", "evaluate.threshold=0.1"]), toy.cache)}
    st = recs[("evaluate", "alpha/full")]
    assert st.state == "stale" and st.reasons == ["params changed (threshold: 0.5 -> 0.1)"]


def test_meter_records_gpu_peak_only_when_the_task_used_cuda(monkeypatch):
    """The engine never imports torch; it reads the allocator peak of a process that
    already has CUDA initialised (a stand-in module here: no GPU on the CI machine)."""
    import types

    from pipeline.measure import Meter

    monkeypatch.delitem(sys.modules, "torch", raising=False)
    assert Meter().stop()["gpu_peak_bytes"] is None  # torch never loaded: nothing to read

    calls = []
    cuda = types.SimpleNamespace(
        is_initialized=lambda: True,
        reset_peak_memory_stats=lambda: calls.append("reset"),
        max_memory_allocated=lambda: 123 << 20,
    )
    monkeypatch.setitem(sys.modules, "torch", types.SimpleNamespace(cuda=cuda))
    m = Meter()
    assert calls == ["reset"]
    assert m.stop()["gpu_peak_bytes"] == 123 << 20

    cuda.is_initialized = lambda: False  # torch loaded, CUDA never initialised (CPU task)
    assert Meter().stop()["gpu_peak_bytes"] is None and calls == ["reset"]


@pytest.mark.parametrize("k", [1, 2, 3, 4])
def test_a_kill_during_a_replacing_commit_keeps_an_entry(tmp_path, monkeypatch, k):
    """A forced recompute replaces an entry; an interruption at the k-th file-system step of
    the replacement leaves the old entry or the new one in place, never neither."""
    import os
    import shutil

    import pipeline.cache as C

    cache = C.Cache(tmp_path / "c")
    cache.ensure()

    def entry(text):
        t = cache.new_tmp("s", "k1")
        (t / "out.txt").write_text(text)
        C.write_json_atomic(t / C.MANIFEST, {"key": "k1", "status": "ok", "outputs": {
            "o": {"path": "out.txt", "kind": "file", "bytes": len(text),
                  "sha256": C.file_sha256(t / "out.txt")}}})
        return t

    cache.commit(entry("old"), "s", "k1")
    new = entry("new!")
    steps = []
    real_rename, real_rmtree = os.rename, shutil.rmtree

    def step(fn):
        def wrapped(*a, **kw):
            steps.append(fn.__name__)
            if len(steps) == k:
                raise KeyboardInterrupt
            return fn(*a, **kw)
        return wrapped

    monkeypatch.setattr(C.os, "rename", step(real_rename))
    monkeypatch.setattr(C.shutil, "rmtree", step(real_rmtree))
    real_exchange = C.exchange_paths
    monkeypatch.setattr(C, "exchange_paths", step(real_exchange))
    try:
        cache.commit(new, "s", "k1")
    except KeyboardInterrupt:
        pass
    monkeypatch.undo()
    check = cache.check("s", "k1")
    assert check.state == "done", (k, steps, check.reason)
    assert (cache.entry_dir("s", "k1") / "out.txt").read_text() in ("old", "new!")


def test_disk_full_stops_the_run_after_the_first_failure(toy):
    """Issue 38 M6: the first "no space left" failure stops the run with one clear message
    naming the cache and its free space; no further task starts."""
    s = toy.run(["train.disk_full_on=alpha"])
    assert s.exit_code == 1 and s.stopped
    assert "disk of the cache" in s.stopped and str(toy.cache.resolve()) in s.stopped and "MiB free" in s.stopped
    assert "run stopped: the disk of the cache" in s.output
    started = {s.plan.tasks[i].id for i in s.outcomes}
    assert "train[alpha]" in started and "train[beta]" not in started
    assert s.output.count("FAILED") >= 1 and "Traceback" not in s.output


def test_disk_full_before_the_run_is_refused_with_the_free_space(toy, monkeypatch):
    import pipeline.run as R
    from pipeline import CacheError

    monkeypatch.setattr(R, "free_bytes", lambda path: 1 << 20)
    with pytest.raises(CacheError, match=r"is full \(1\.0 MiB free\)"):
        toy.run()


def _tmpfs(path, size):
    import subprocess

    path.mkdir(parents=True, exist_ok=True)
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], capture_output=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here ({r.stderr.decode(errors='replace').strip()[:80]}): "
                    "the full-disk run is tested with an injected ENOSPC above")
    return path


@pytest.mark.parametrize("fill", ["all", "almost"])
def test_a_real_full_cache_disk(toy, tmp_path, fill, monkeypatch):
    """On a cache disk that is full (or fills up during the run), `cobgs run` neither crashes
    in its failure handler nor goes on computing: the up-front check is switched off here
    so that the tasks meet the full disk themselves."""
    import subprocess

    import pipeline.run as R

    monkeypatch.setattr(R, "MIN_FREE_BYTES", 0)
    mnt = _tmpfs(tmp_path / "small", "1m")
    try:
        toy.cache = mnt / "cache"
        if fill == "all":
            toy.cache.mkdir()
            for sub in ("entries", "failed", "tmp", "locks", "refs"):
                (toy.cache / sub).mkdir()
        import os

        big = mnt / "filler"
        fd = os.open(big, os.O_WRONLY | os.O_CREAT)  # unbuffered: fill to the last block
        try:
            while True:
                os.write(fd, b"\0" * 4096)
        except OSError:
            pass
        if fill == "almost":  # a few blocks left: the run starts, then the writes fail
            os.ftruncate(fd, os.fstat(fd).st_size - 16 * 1024)
        os.close(fd)
        from pipeline import CacheError

        try:
            s = toy.run()
        except CacheError as exc:  # the cache folder itself cannot be written: said so
            assert str(toy.cache) in str(exc) and ("MiB free" in str(exc) or "cannot" in str(exc))
            return
        assert s.exit_code == 1 and s.stopped and "Traceback" not in s.output
        assert len(s.outcomes) < s.total  # stopped, not every task computed and failed
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


def test_a_fully_cached_run_is_served_from_a_read_only_cache(toy, monkeypatch):
    """Issue 38 L9: a read-only cache (a shared, published one) serves a run whose every task
    is cached; a run that must compute is still refused, saying why."""
    import os

    import pipeline.cache as C
    from pipeline import CacheError

    assert toy.run().exit_code == 0
    refs = sorted(p for p in (toy.cache / "refs").rglob("*") if p.is_file())
    stamps = [p.stat().st_mtime_ns for p in refs]
    real = os.access
    monkeypatch.setattr(C.os, "access", lambda p, mode: False if mode == os.W_OK else real(p, mode))
    s = toy.run()
    assert s.exit_code == 0 and "is read-only; every task is cached" in s.output
    assert all(o.state == "cached" for o in s.outcomes.values())
    assert [p.stat().st_mtime_ns for p in refs] == stamps  # nothing written
    with pytest.raises(CacheError, match="not writable"):
        toy.run(["train.iterations=11"])


def test_gc_removes_memo_temporaries_of_killed_runs(toy, executions):
    """Issue 44 L8: a memo write killed between its temporary file and the rename left
    ``fingerprints/.<hash>.json.<pid>.<id>.tmp``, which gc never removed. A live run's
    temporary (its pid alive, recent) is kept."""
    import os

    toy.run()
    memo = toy.cache / "fingerprints"
    memo.mkdir(exist_ok=True)
    dead = memo / f".{'a' * 32}.json.{2 ** 22 + 1}.140000.tmp"  # above pid_max: no such process
    live = memo / f".{'b' * 32}.json.{os.getpid()}.140001.tmp"
    dead.write_text("{")
    live.write_text("{")
    keep = referenced_keys([str(toy.path)], toys.registry(), [], toy.cache)
    report = collect(toy.cache, keep, dry_run=True)
    assert any(dead.name in line for line in report.lines) and dead.exists()
    collect(toy.cache, keep)
    assert not dead.exists() and live.exists()


SHARING = toys.WORKFLOW + """
[axes.scene.alpha_long]
shares = "alpha"
kind = "synthetic"
train = { iterations = 30 }
"""


def test_a_value_that_shares_reuses_the_identical_tasks_only(toy, executions):
    """``shares``: alpha_long's load is alpha's (one key, one entry, computed once, by alpha);
    its training (other params) and everything downstream are its own; alpha's and beta's
    keys are those of the workflow without alpha_long."""
    toy.run()
    before = {(r.stage, r.item.id): r.key for r in entries(toy.load(), toy.cache)}
    executions.reset()
    toy.load(text=SHARING)
    s = toy.run()
    assert s.exit_code == 0, s.output
    # the cache written without alpha_long serves alpha's and beta's tasks and alpha_long's load
    assert executions.count() == {"train alpha_long": 1, "refine alpha_long/full": 1,
                                  "refine alpha_long/nosplit": 1, "evaluate alpha_long/full": 1,
                                  "evaluate alpha_long/nosplit": 1, "summary ": 1}
    recs = states(toy)
    assert recs[("load", "alpha_long")].key == recs[("load", "alpha")].key
    assert recs[("load", "alpha_long")].entry_dir == recs[("load", "alpha")].entry_dir
    assert recs[("load", "alpha_long")].state == "done"
    assert recs[("train", "alpha_long")].key != recs[("train", "alpha")].key
    weights = recs[("train", "alpha_long")].output("model") / "weights.txt"
    assert weights.read_text().startswith("scene=alpha kind") and "iterations=30" in weights.read_text()
    assert {k: r.key for k, r in recs.items() if k in before and k[0] != "summary"} == \
        {k: v for k, v in before.items() if k[0] != "summary"}  # (summary gathers alpha_long too)
    # the alias alone: the twin's shared task comes along, nothing else of the twin's
    shutil.rmtree(toy.cache)
    executions.reset()
    s = toy.run(items="alpha_long")
    assert s.exit_code == 0, s.output
    assert executions.count() == {"load alpha": 1, "train alpha_long": 1, "refine alpha_long/full": 1,
                                  "refine alpha_long/nosplit": 1, "evaluate alpha_long/full": 1,
                                  "evaluate alpha_long/nosplit": 1}
    # a forced shared task is recomputed once, by its twin
    executions.reset()
    toy.run(force=("load",), only=("load",))
    assert executions.count() == {"load alpha": 1, "load beta": 1}
    # different params: a task of its own, keyed as itself
    toy.load(text=SHARING + 'load = { size = 5 }\n')
    executions.reset()
    toy.run(only=("load",))
    assert executions.count() == {"load alpha_long": 1}


def test_an_override_of_the_twin_alone_leaves_the_sharing_values_entry_served(toy, executions):
    """Issue 56 M7: alpha_long's load was alpha's entry; adding an override to alpha alone
    re-keyed alpha_long's unchanged load as its own, so it reran, although the entry for
    exactly its config was cached. Now only alpha's load runs; alpha_long's is served from
    the entry alpha computed while the two were the same, and keeps it when alpha returns."""
    toy.load(text=SHARING)
    assert toy.run().exit_code == 0
    old = states(toy)[("load", "alpha_long")]
    changed = SHARING.replace('[axes.scene.alpha]\nkind = "synthetic"\n',
                              '[axes.scene.alpha]\nkind = "synthetic"\nload = { size = 5 }\n')
    assert changed != SHARING
    toy.load(text=changed)
    executions.reset()
    s = toy.run()
    assert s.exit_code == 0, s.output
    ran = executions.count()
    assert ran["load alpha"] == 1 and "load alpha_long" not in ran and "train alpha_long" not in ran, ran
    recs = states(toy)
    assert recs[("load", "alpha_long")].state == "done" and recs[("load", "alpha_long")].key == old.key
    assert recs[("load", "alpha")].key != old.key
    assert "cached" in s.output.split("load      alpha_long")[1].splitlines()[0], s.output
    # --dry-run on a fresh cache says which tasks share their twin's entry (issue 56, low)
    import io

    out = io.StringIO()
    run_workflow(toy.load(text=SHARING), RunOptions(cache_dir=toy.folder / "fresh", dry_run=True), stream=out)
    line = next(ln for ln in out.getvalue().splitlines() if "load" in ln and "alpha_long" in ln)
    assert "shared: load[alpha] computes the one entry both use" in line, out.getvalue()
    assert "more share their twin's entry" in out.getvalue()
    toy.load(text=changed)
    # forced, the sharing value's task computes its own entry (keyed as itself)
    executions.reset()
    toy.run(force=("load",), only=("load",), items="alpha_long")
    assert executions.count() == {"load alpha_long": 1}


@pytest.mark.parametrize("value, message", [
    ('"gamma"', "expected the name of another scene value, got 'gamma'"),
    ('"alpha_long"', "expected the name of another scene value, got 'alpha_long'"),
    ("3", "expected the name of another scene value, got 3"),
])
def test_shares_names_another_value(toy, value, message):
    with pytest.raises(WorkflowError, match=message):
        toy.load(text=SHARING.replace('shares = "alpha"', f"shares = {value}"))


def test_shares_has_no_chains(toy):
    text = SHARING + '\n[axes.scene.alpha_longer]\nshares = "alpha_long"\nkind = "synthetic"\n'
    with pytest.raises(WorkflowError, match="'alpha_long' itself shares 'alpha'"):
        toy.load(text=text)
