"""Fixtures for the engine tests: a toy workflow in a temp folder and an execution log."""

from __future__ import annotations

import io
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:  # pipeline_toys must import the same way in every process
    sys.path.insert(0, str(HERE))

import pipeline_toys as toys  # noqa: E402
from pipeline import RunOptions, load_workflow, run_workflow  # noqa: E402
from pipeline_testutil import Executions  # noqa: E402


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
