"""The workflow commands through a real ``cobgs`` process (toy stages plugged in)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from pipeline_testutil import REPO, cli_env


def cobgs(*args, cwd=REPO, check=None, **env):
    proc = subprocess.run([sys.executable, "-m", "stages.commands.cli", *map(str, args)], cwd=cwd,
                          env=cli_env(**env), capture_output=True, text=True, timeout=120)
    if check is not None:
        assert proc.returncode == check, proc.stdout + proc.stderr
    return proc


def test_run_status_and_rerun(toy, executions):
    wf, cache = toy.path, toy.cache
    out = cobgs("run", wf, "--cache-dir", cache, check=0).stdout
    assert f"cache {cache}" in out and "13 done" in out
    assert "[ 3/13] train     alpha          done" in out
    out = cobgs("run", wf, "--cache-dir", cache, "-q", check=0).stdout
    assert "cached" not in out.split("run finished")[0] and "13 cached" in out
    out = cobgs("status", wf, "--cache-dir", cache, check=0).stdout
    assert out.count(" done ") == 13 and "13 done" in out
    line = next(l for l in out.splitlines() if l.startswith("train     beta"))
    assert " s " in line and "MiB" in line  # wall time and peak memory columns
    out = cobgs("run", wf, "--cache-dir", cache, "--dry-run", "--set", "refine.split=false",
                check=0).stdout
    assert "params changed (split: true -> false)" in out
    assert "refine    alpha/nosplit  cached" in out  # nosplit already had split = false
    out = cobgs("status", wf, "--cache-dir", cache, "--set", "refine.split=false",
                check=0).stdout
    assert "refine    alpha/full     stale" in out
    assert executions.stages()["summary"] == 1


def test_failures_exit_non_zero_and_status_shows_the_log(toy):
    wf, cache = toy.path, toy.cache
    proc = cobgs("run", wf, "--cache-dir", cache, "--set", "train.fail_on=alpha", check=1)
    assert "FAILED  train[alpha]: RuntimeError: toy training diverged on alpha" in proc.stdout
    assert "cobgs run: 6 task(s) not done: train[alpha], refine[alpha/full]" in proc.stderr
    out = cobgs("status", wf, "--cache-dir", cache, "--set", "train.fail_on=alpha",
                "--logs", check=0).stdout
    assert "train     alpha          failed" in out
    assert "FAILED train[alpha]: RuntimeError: toy training diverged" in out
    assert "/failed/train/" in out and "Traceback (most recent call last)" in out


@pytest.mark.parametrize("text, args, env, message", [
    ("[params.evaluate]\nthreshhold = 1\n", (), {}, "params.evaluate.threshhold: unknown "
                                                    "param 'threshhold'"),
    ("[axes.scene.gamma]\npath = '${TOY_MISSING_DIR}/a'\n", (), {},
     "environment variable TOY_MISSING_DIR is not set"),
    (None, ("--set", "train.iterations=x"), {}, "--set: train.iterations: expected an integer"),
    (None, ("--only", "nope"), {}, "--only: unknown stage 'nope'"),
    (None, ("--executor", "ray"), {"PYTHONWARNINGS": "ignore"}, "pip install 'cobgs[ray]'"),
    # issue 56 (low): an empty value (a script's unset variable) was taken as "nothing"
    (None, ("--force", ""), {}, "argument --force: it is empty"),
    (None, ("--items", " "), {}, "argument --items: it is empty"),
    (None, ("--cache-dir", ""), {}, "argument --cache-dir: it is empty"),
])
def test_errors_are_one_clear_line(toy, text, args, env, message):
    if text is not None:
        toy.path.write_text(toy.path.read_text() + text)
    if "--executor" in args:  # hide an installed Ray from this process
        code = ("import sys; sys.modules['ray'] = None; from stages.commands.cli import main; "
                f"sys.exit(main({['run', str(toy.path), '--cache-dir', str(toy.cache), *args]!r}))")
        proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=cli_env(**env),
                              capture_output=True, text=True, timeout=120)
    else:
        proc = cobgs("run", toy.path, *(() if "--cache-dir" in args else ("--cache-dir", toy.cache)), *args)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert message in proc.stderr and "Traceback" not in proc.stderr
    assert proc.stderr.splitlines()[-1].startswith("cobgs run: error: ")  # (argparse prints the usage first)


def test_cache_commands(toy, tmp_path):
    wf, cache = toy.path, toy.cache
    cobgs("run", wf, "--cache-dir", cache, check=0)
    cobgs("run", wf, "--cache-dir", cache, "--set", "evaluate.threshold=0.1", check=0)
    out = cobgs("cache", "ls", "--cache-dir", cache, check=0).stdout
    # 13 + four evaluate entries and a summary (the metrics hold the threshold).
    assert "18 entries" in out and "evaluate" in out and "alpha/full" in out
    # The threshold=0.1 entries are each slot's latest run: gc keeps them...
    out = cobgs("cache", "gc", wf, "--cache-dir", cache, "--dry-run", check=0).stdout
    assert "would remove 0 entries" in out
    cobgs("run", wf, "--cache-dir", cache, check=0)
    # ...until the workflow runs again with its own settings.
    out = cobgs("cache", "gc", wf, "--cache-dir", cache, "--dry-run", check=0).stdout
    assert "would remove 5 entries" in out and "entries/evaluate/" in out
    proc = cobgs("cache", "gc", wf, "--cache-dir", cache, check=2)  # no terminal to ask on: --yes
    assert "would remove 5 entries/records" in proc.stderr and "pass --yes" in proc.stderr, proc.stderr
    out = cobgs("cache", "gc", wf, "--cache-dir", cache, "--yes", check=0).stdout
    assert "removed 5 entries" in out and "kept 13 entries" in out
    assert "13 entries" in cobgs("cache", "ls", "--cache-dir", cache, check=0).stdout
    # Same size, different bytes: only a re-hash can tell.
    entry = next((cache / "entries" / "load").iterdir())
    data = entry / "out" / "data.txt"
    data.write_text(data.read_text().replace("alpha", "ALPHA").replace("beta", "BETA"))
    out = cobgs("cache", "verify", "--cache-dir", cache, check=1).stdout
    assert "does not match its recorded hash" in out and "12 of 13" in out
    cobgs("cache", "verify", "--cache-dir", cache, "--fix", check=0)
    out = cobgs("run", wf, "--cache-dir", cache, check=0).stdout
    assert "1 done, 12 cached" in out  # the load entry verify removed is recomputed


def test_cache_dir_defaults(toy, tmp_path):
    cobgs("run", toy.path, cwd=tmp_path, check=0)
    assert (tmp_path / "runs" / "cache" / "entries" / "summary").is_dir()
    other = tmp_path / "from_env"
    cobgs("run", toy.path, cwd=tmp_path, COBGS_CACHE_DIR=str(other), check=0)
    assert (other / "entries" / "summary").is_dir()


def test_stages_listing(toy):
    out = cobgs("stages", check=0).stdout
    assert "refine v1  per scene x method  ['model'] -> ['refined']  (uses device)" in out
    out = cobgs("stages", "--toml", check=0).stdout
    assert "[params.train]\niterations = 10\nfail_on = \"\"" in out


def test_wrong_shaped_cache_files_are_corrupt_entries_not_crashes(toy):
    """Valid JSON of the wrong shape in the cache (a manifest whose folder sizes are a list,
    a refs file holding a list, a failure record holding a string) is treated like any
    corrupt file: every command still works, the entry is recomputed."""
    import json

    from pipeline import entries

    wf, cache = toy.path, toy.cache
    cobgs("run", wf, "--cache-dir", cache, check=0)
    recs = {(r.stage, r.item.id): r for r in entries(toy.load(), cache)}
    train = recs[("train", "alpha")]
    man = train.entry_dir / "manifest.json"
    m = json.loads(man.read_text())
    name = next(iter(m["outputs"]))
    m["outputs"][name] = {"path": m["outputs"][name]["path"], "kind": "dir", "sizes": [1, 2]}
    man.write_text(json.dumps(m))
    refine = recs[("refine", "beta/full")]
    other = recs[("evaluate", "alpha/full")].entry_dir / "manifest.json"
    m2 = json.loads(other.read_text())
    m2["outputs"] = {"x": [1]}
    other.write_text(json.dumps(m2))
    refs = sorted((cache / "refs").rglob("*.json"))
    for r in refs[:3]:
        if r.name != "workflow.json":
            r.write_text("[1]")
    failed = cache / "failed" / "refine" / refine.key
    failed.mkdir(parents=True)
    (failed / "manifest.json").write_text('"x"')
    (cache / "refs" / next(p.name for p in (cache / "refs").iterdir()) / "workflow.json").write_text("7")
    for args in (("status", wf), ("cache", "ls"), ("cache", "verify"), ("run", wf, "--dry-run")):
        proc = cobgs(*args, "--cache-dir", cache)
        assert proc.returncode in (0, 1) and "Traceback" not in proc.stderr, (args, proc.stderr)
    out = cobgs("run", wf, "--cache-dir", cache, check=0).stdout
    # the entries with malformed manifests are recomputed (and what depends on them)
    assert "train     alpha          done" in out and "evaluate  alpha/full     done" in out, out
    proc = cobgs("cache", "gc", wf, "--cache-dir", cache, "--yes")
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr
    out = cobgs("status", wf, "--cache-dir", cache, check=0).stdout
    assert out.count(" done ") == 13


def test_a_closed_pipe_ends_quietly():
    """`cobgs stages --toml | head -1`: the reader leaves early; no BrokenPipe traceback,
    exit status 141 (what a shell reports for SIGPIPE)."""
    proc = subprocess.Popen([sys.executable, "-m", "stages.commands.cli", "stages", "--toml"], cwd=REPO,
                            env=cli_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.readline()
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=60) in (0, 141) and "Traceback" not in err and "BrokenPipe" not in err, err


def test_progress_of_a_running_task_reaches_a_non_tty_console(toy):
    """Not on a terminal (a CI log, `cobgs run ... > log`), a running task's progress is a
    console line every few seconds (here: every update) with its count, percentage and
    ETA, not only a line in the entry's log file."""
    proc = cobgs("run", toy.path, "--cache-dir", toy.cache, "--items", "alpha/full", check=0,
                 COBGS_PROGRESS_INTERVAL_S="0", PIPELINE_TOYS_SLEEP="0.05")
    lines = [l.strip() for l in proc.stderr.splitlines() if l.strip().startswith("refine[alpha/full]")]
    assert lines and lines[0].startswith("refine[alpha/full] refining: 1/3 (33%)") and "ETA" in lines[0], proc.stderr
    assert any(l.startswith("refine[alpha/full] refining: 3/3 (100%)") for l in lines), lines


@pytest.mark.parametrize("edit, where", [
    (lambda m: m.update(log="/etc/passwd"), "the log points outside its entry"),
    (lambda m: m.update(log="../../../../../../etc/passwd"), "the log points outside its entry"),
    (lambda m: next(iter(m["outputs"].values())).update(path="../../../../etc/hostname"),
     "points outside its entry"),
    (lambda m: next(iter(m["outputs"].values())).update(path="/etc"), "points outside its entry"),
])
def test_manifest_paths_outside_the_entry_make_it_corrupt(toy, edit, where):
    """Issue 38 M5: every path read from a manifest must resolve inside its entry (a shared
    NFS / Ray cache is written by others); otherwise the entry is corrupt, never served."""
    import json

    wf, cache = toy.path, toy.cache
    cobgs("run", wf, "--cache-dir", cache, check=0)
    entry = next((cache / "entries" / "load").iterdir())
    m = json.loads((entry / "manifest.json").read_text())
    edit(m)
    (entry / "manifest.json").write_text(json.dumps(m))
    out = cobgs("cache", "verify", "--cache-dir", cache, check=1).stdout
    assert where in out and "12 of 13" in out
    out = cobgs("status", wf, "--cache-dir", cache, check=0).stdout
    assert "corrupt" in out.split("\n")[1] or "corrupt" in out, out
    proc = cobgs("run", wf, "--cache-dir", cache, check=0)  # recomputed, not served
    assert "Traceback" not in proc.stderr
    m2 = json.loads(next((cache / "entries" / "load").iterdir()).joinpath("manifest.json").read_text())
    assert m2.get("log", "log.txt") == "log.txt"


def test_cache_commands_refuse_a_folder_that_is_no_cache(toy, tmp_path):
    """Issue 38 L8: a mistyped --cache-dir is an error, not "removed 0 entries"."""
    for args in (("cache", "gc", toy.path), ("cache", "ls"), ("cache", "verify")):
        proc = cobgs(*args, "--cache-dir", tmp_path / "typo", check=2)
        assert "typo does not exist" in proc.stderr and "Traceback" not in proc.stderr


def test_cache_gc_on_a_terminal_lists_and_asks(toy, tmp_path):
    """Issue 38 L8: on a terminal, gc lists what it would remove and asks; "n" keeps all,
    --yes does not ask."""
    import os
    import pty

    wf, cache = toy.path, toy.cache
    cobgs("run", wf, "--cache-dir", cache, check=0)
    other = tmp_path / "other.toml"  # a workflow that shares nothing: gc would remove almost all
    other.write_text(wf.read_text().replace("[axes.scene.alpha]", "[axes.scene.zeta]"))
    before = cobgs("cache", "ls", "--cache-dir", cache, check=0).stdout.splitlines()[-1]
    master, slave = pty.openpty()
    os.write(master, b"n\n")
    proc = subprocess.run([sys.executable, "-m", "stages.commands.cli", "cache", "gc", str(other),
                           "--cache-dir", str(cache)], cwd=REPO, env=cli_env(), stdin=slave,
                          capture_output=True, text=True, timeout=120)
    os.close(slave)
    os.close(master)
    assert proc.returncode == 1 and "would remove entries/" in proc.stdout and "[y/N]" in proc.stdout
    assert "nothing removed" in proc.stdout
    assert cobgs("cache", "ls", "--cache-dir", cache, check=0).stdout.splitlines()[-1] == before
    out = cobgs("cache", "gc", other, "--cache-dir", cache, "--yes", check=0).stdout
    assert "removed" in out and "[y/N]" not in out


def test_a_workflow_file_that_is_no_regular_file_is_refused_at_once(tmp_path):
    """Issue 56 (low): `cobgs run /dev/zero` read forever; a FIFO blocked."""
    import os

    fifo = tmp_path / "w.toml"
    os.mkfifo(fifo)
    for path in ("/dev/zero", fifo, tmp_path):
        proc = cobgs("run", path, "--cache-dir", tmp_path / "c", check=2)
        assert "not a regular file" in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
