"""Fixtures for the engine tests: a toy workflow in a temp folder and an execution log."""

from __future__ import annotations

import io
import os
import sys
from collections import Counter
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
if str(HERE) not in sys.path:  # pipeline_toys must import the same way in every process
    sys.path.insert(0, str(HERE))

import pipeline_toys as toys  # noqa: E402
from pipeline import RunOptions, load_workflow, run_workflow  # noqa: E402


class Executions:
    """Reads the ``$PIPELINE_TOYS_LOG`` file the toy stages append to."""

    def __init__(self, path: Path):
        self.path = path

    def lines(self) -> list[str]:
        return self.path.read_text().splitlines() if self.path.exists() else []

    def count(self) -> Counter:
        return Counter(self.lines())

    def stages(self) -> Counter:
        return Counter(line.split(" ")[0] for line in self.lines())

    def reset(self) -> None:
        self.path.unlink(missing_ok=True)


@pytest.fixture
def executions(tmp_path, monkeypatch) -> Executions:
    path = tmp_path / "executions.log"
    monkeypatch.setenv("PIPELINE_TOYS_LOG", str(path))
    return Executions(path)


@pytest.fixture
def toy(tmp_path, executions):
    """A helper running the toy workflow in-process: ``toy.run(sets=..., **options)``."""

    class Toy:
        folder = tmp_path
        cache = tmp_path / "cache"
        path = toys.write_workflow(tmp_path)

        def load(self, sets=(), registry=None, text=None):
            if text is not None:
                self.path.write_text(text)
            return load_workflow(self.path, registry or toys.registry(), sets)

        def run(self, sets=(), registry=None, **options):
            wf = self.load(sets, registry)
            out = io.StringIO()
            summary = run_workflow(wf, RunOptions(cache_dir=self.cache, package_version="t",
                                                  **options), stream=out)
            summary.output = out.getvalue()
            return summary

    return Toy()


def cli_env(**extra: str) -> dict[str, str]:
    """Environment for running ``cobgs`` in a subprocess with the toy stages plugged in."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(HERE), str(REPO), env.get("PYTHONPATH", "")])
    env["COBGS_STAGE_MODULES"] = "pipeline_toys"
    env.pop("COBGS_CACHE_DIR", None)
    env.update(extra)
    return env
