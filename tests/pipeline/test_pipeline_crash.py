"""Crash safety through real processes: SIGKILL mid-write, Ctrl-C, two concurrent runs."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pipeline_testutil import REPO, cli_env
from pipeline import entries
from pipeline.cache import Cache


def start_run(toy, *args, **env):
    if "PIPELINE_TOYS_HANG" in env:
        Path(env["PIPELINE_TOYS_HANG"] + ".arm").touch()
    cmd = [sys.executable, "-m", "stages.commands.cli", "run", str(toy.path), "--cache-dir",
           str(toy.cache), *args]
    return subprocess.Popen(cmd, cwd=REPO, env=cli_env(**env), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)


def wait_for(path: Path, proc, timeout=60.0) -> str:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if path.exists() and path.read_text():
            return path.read_text()
        if proc.poll() is not None:
            raise AssertionError(f"run ended early:\n{proc.stdout.read()}")
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    raise AssertionError("the stage never reached its hang point")


def by_task(toy):
    return {(r.stage, r.item.id): r for r in entries(toy.load(), toy.cache)}


def test_sigkill_mid_write_leaves_nothing_done_and_the_next_run_recomputes(toy, executions):
    marker = toy.folder / "hang"
    proc = start_run(toy, PIPELINE_TOYS_HANG=str(marker), PIPELINE_TOYS_HANG_ITEM="alpha/full")
    wait_for(marker, proc)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    recs = by_task(toy)
    target = recs[("refine", "alpha/full")]
    assert target.state == "missing" and target.key is not None
    assert not Cache(toy.cache).entry_dir("refine", target.key).exists()
    leftovers = list((toy.cache / "tmp").glob(f"refine.{target.key}.*"))
    assert len(leftovers) == 1  # the half-written output, never read by anyone
    assert (leftovers[0] / "out" / "refined.txt").read_text() == "partial"
    assert recs[("train", "alpha")].state == "done"  # finished work survives the kill
    lock = Cache(toy.cache).lock("refine", target.key)
    assert lock.acquire(blocking=False)  # the kernel dropped the dead run's lock
    lock.release()

    executions.reset()
    summary = toy.run()
    assert summary.exit_code == 0
    assert executions.count()["refine alpha/full"] == 1
    assert "train" not in executions.stages()
    done = by_task(toy)[("refine", "alpha/full")]
    assert done.state == "done" and "partial" not in done.output("refined").read_text()
    assert not list((toy.cache / "tmp").glob(f"refine.{target.key}.*"))


def test_sigkill_of_a_pool_worker_fails_only_its_task(toy, executions):
    marker = toy.folder / "hang"
    proc = start_run(toy, "--jobs", "2", PIPELINE_TOYS_HANG=str(marker),
                     PIPELINE_TOYS_HANG_ITEM="beta/nosplit")
    worker = int(wait_for(marker, proc))
    assert worker != proc.pid
    os.kill(worker, signal.SIGKILL)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 1, out
    assert "worker process died without a result (killed by signal 9)" in out
    assert "refine[beta/nosplit]" in out.splitlines()[-1]
    recs = by_task(toy)
    assert recs[("refine", "beta/nosplit")].state == "failed"
    assert recs[("evaluate", "beta/nosplit")].state == "missing"
    assert recs[("evaluate", "alpha/nosplit")].state == "done"
    assert recs[("evaluate", "beta/full")].state == "done"
    assert toy.run().exit_code == 0  # the retry succeeds and clears the failure
    assert by_task(toy)[("refine", "beta/nosplit")].state == "done"


def _gone(pid: int, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        try:  # a zombie (exited, not yet reaped by its new parent) is gone too
            if Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] == "Z":
                return True
        except OSError:
            return True
        time.sleep(0.05)
    return False


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM])
def test_a_killed_driver_leaves_no_worker_behind(toy, sig):
    """Killing only the driver's pid (not its process group, as the OOM killer or `kill PID`
    does) ends its forked task workers within seconds instead of leaving them under PID 1."""
    marker = toy.folder / "hang"
    proc = start_run(toy, "--jobs", "2", PIPELINE_TOYS_HANG=str(marker),
                     PIPELINE_TOYS_HANG_ITEM="beta/nosplit")
    worker = int(wait_for(marker, proc))
    assert worker != proc.pid
    os.kill(proc.pid, sig)
    proc.wait(timeout=30)
    try:
        assert _gone(worker, 5.0), f"worker {worker} outlived the killed driver"
    finally:
        try:
            os.kill(worker, signal.SIGKILL)
        except ProcessLookupError:
            pass


@pytest.mark.parametrize("jobs", ["1", "2"])
def test_ctrl_c_discards_running_entries_and_keeps_finished_ones(toy, jobs):
    marker = toy.folder / "hang"
    proc = start_run(toy, "--jobs", jobs, PIPELINE_TOYS_HANG=str(marker),
                     PIPELINE_TOYS_HANG_ITEM="alpha/full")
    wait_for(marker, proc)
    os.killpg(proc.pid, signal.SIGINT)  # what a terminal's Ctrl-C does
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 130, out
    assert "interrupted" in out and "Traceback" not in out
    # the summary line says what each number counts, out of the run's 13 tasks
    line = next(l for l in out.splitlines() if l.startswith("interrupted:"))
    assert re.match(r"interrupted: \d+ of 13 tasks finished \(.*\); \d+ running or waiting on them "
                    r"were stopped, \d+ not started", line), line
    recs = by_task(toy)
    key = recs[("refine", "alpha/full")].key
    assert recs[("refine", "alpha/full")].state == "missing"
    assert not list((toy.cache / "tmp").glob(f"refine.{key}.*"))  # cleaned, not left over
    assert not (toy.cache / "failed" / "refine" / key).exists()  # Ctrl-C is not a failure
    assert recs[("train", "alpha")].state == "done"


def test_two_concurrent_runs_compute_each_entry_once(toy, executions):
    env = {"PIPELINE_TOYS_SLEEP": "0.15"}
    first = start_run(toy, **env)
    second = start_run(toy, "--jobs", "2", **env)
    out1, _ = first.communicate(timeout=120)
    out2, _ = second.communicate(timeout=120)
    assert first.returncode == 0, out1
    assert second.returncode == 0, out2
    lines = executions.lines()
    assert len(lines) == 13 and len(set(lines)) == 13, lines  # nothing computed twice
    assert {r.state for r in by_task(toy).values()} == {"done"}
    # Both runs saw all 13 tasks finish, between them computing each one once.
    # (progress lines only: the summary line of a run that did everything says "13 done (")
    done = [ln for ln in (out1 + out2).splitlines() if ln.startswith("[") and " done " in ln]
    assert len(done) == 13, out1 + out2
    assert "finished by another run" in out1 + out2 or " cached " in out1 + out2
