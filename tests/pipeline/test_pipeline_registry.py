"""stages/registry.py: how stage modules are collected into the program's registry."""

from __future__ import annotations

import io
import sys
import types
from dataclasses import dataclass
from pathlib import Path

import pytest

import pipeline_toys as toys
from pipeline import PipelineError, RunOptions, Stage, load_workflow, run_workflow
from stages import registry as R


def test_env_modules_are_added(monkeypatch):
    monkeypatch.setattr(R, "STAGE_MODULES", ())
    monkeypatch.setenv(R.EXTRA_MODULES_ENV, "pipeline_toys")
    reg = R.load_registry()
    assert list(reg.graph().order) == ["load", "train", "refine", "evaluate", "summary"]
    assert reg.stages["refine"] is toys.REFINE


def test_zero_stages_still_work(monkeypatch, tmp_path):
    monkeypatch.setattr(R, "STAGE_MODULES", ())
    monkeypatch.delenv(R.EXTRA_MODULES_ENV, raising=False)
    reg = R.load_registry()
    assert reg.stages == {} and reg.graph().order == ()
    path = tmp_path / "empty.toml"
    path.write_text("[workflow]\nname = 'empty'\n[axes.scene.a]\n")
    out = io.StringIO()
    summary = run_workflow(load_workflow(path, reg), RunOptions(cache_dir=tmp_path / "c"),
                           stream=out)
    assert summary.exit_code == 0 and "nothing to do" in out.getvalue()


@dataclass(frozen=True)
class SceneAttrs:
    path: Path = Path(".")


def test_module_contract_and_errors(monkeypatch):
    mod = types.ModuleType("fake_stage_mod")
    mod.STAGE = Stage(name="fake", version=1, run=lambda c, i: {}, outputs=("f",))
    mod.AXIS_SCHEMAS = {"scene": SceneAttrs}
    monkeypatch.setitem(sys.modules, "fake_stage_mod", mod)
    monkeypatch.setattr(R, "STAGE_MODULES", ("fake_stage_mod",))
    monkeypatch.delenv(R.EXTRA_MODULES_ENV, raising=False)
    reg = R.load_registry()
    assert list(reg.stages) == ["fake"] and reg.axis_schemas == {"scene": SceneAttrs}
    with pytest.raises(PipelineError, match="cannot import stage module 'no_such_mod'"):
        R.load_registry(["no_such_mod"])
    with pytest.raises(PipelineError, match="'json' defines neither STAGE nor STAGES"):
        R.load_registry(["json"])
    mod.STAGES = ("not a stage",)
    with pytest.raises(PipelineError, match="is not a pipeline Stage"):
        R.load_registry()
