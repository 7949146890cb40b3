"""Fixtures of the report tests: a recorded run (real engine, toy stages) and its report,
each built once per session because every test only reads them."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:  # the fixture stages must import the same way everywhere
    sys.path.insert(0, str(HERE))

import report_fixture_run as fixture_run  # noqa: E402
from report_fixture_run import Recorded  # noqa: E402


@pytest.fixture(scope="session")
def recorded(tmp_path_factory) -> Recorded:
    """Two scenes, five methods (COB-GS, two ablation rows, two peers); the FlashSplat
    refine of s2/ball fails on purpose, so its segment and evaluate never run."""
    return Recorded(tmp_path_factory.mktemp("recorded"))


@pytest.fixture(scope="session")
def report(recorded, tmp_path_factory) -> Path:
    """index.html of the recorded run's report (built once, read by many tests)."""
    return recorded.build(tmp_path_factory.mktemp("report") / "report")


@pytest.fixture(scope="session")
def demo_report(tmp_path_factory) -> Path:
    """The embedded demo workflow (workflows/demo.toml) run for real (~1 min on 2 cores) and
    reported with the default options, as `make demo` does (without its turntables)."""
    from stages.commands.report import build_report
    from stages.commands.cli import main

    root = tmp_path_factory.mktemp("demo")
    workflow = Path(__file__).resolve().parents[2] / "workflows" / "demo.toml"
    assert main(["run", str(workflow), "--cache-dir", str(root / "cache")]) == 0
    return build_report(workflow, out_dir=root / "report", cache_dir=root / "cache")
