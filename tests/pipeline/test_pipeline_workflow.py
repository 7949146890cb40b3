"""Workflow TOML: schema errors, env vars, paths, --set coercion, overrides, items."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional

import pytest

import pipeline_toys as toys
from pipeline import Item, Plan, Registry, Stage, WorkflowError, load_workflow


def write(tmp_path, text, name="wf.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_params_layers_and_precedence(toy):
    wf = toy.load(sets=["evaluate.threshold=0.9"])
    plan = Plan(wf)
    # [params.train] applies to every scene; beta overrides it.
    assert plan.find("train", "alpha").params.value.iterations == 10
    assert plan.find("train", "beta").params.value.iterations == 20
    # The method's override applies to both scenes; defaults elsewhere.
    assert plan.find("refine", "alpha/nosplit").params.value.split is False
    assert plan.find("refine", "beta/full").params.value.split is True
    # --set beats everything; typed to the field (float), "0.9" parsed from text.
    assert plan.find("evaluate", "beta/nosplit").params.value.threshold == 0.9
    # A --set on a stage also beats an item override.
    wf = toy.load(sets=["train.iterations=5", "device=cuda"])
    assert Plan(wf).find("train", "beta").params.value.iterations == 5
    assert wf.settings.device == "cuda"


def test_fan_out_and_fan_in_bindings(toy):
    plan = Plan(toy.load())
    refine = plan.find("refine", "beta/nosplit")
    (b,) = refine.bindings
    assert not b.fan_in and plan.tasks[b.sources[0]].id == "train[beta]"
    summary = plan.find("summary", "")
    (b,) = summary.bindings
    assert b.fan_in
    assert sorted(plan.tasks[s].item.id for s in b.sources) == \
        ["alpha/full", "alpha/nosplit", "beta/full", "beta/nosplit"]
    assert len(plan.tasks) == 2 + 2 + 4 + 4 + 1


AXES = "[axes.scene.a]\n[axes.method.m]\n"


@pytest.mark.parametrize("text, key, message", [
    ("[workflow]\nnmae = 'x'\n", "workflow.nmae", "did you mean 'name'"),
    ("[paramz.train]\n", "paramz", "unknown key"),
    (AXES + "[params.train]\niteratons = 3\n", "params.train.iteratons",
     "did you mean 'iterations'"),
    (AXES + "[params.train]\niterations = 'many'\n", "params.train.iterations",
     "expected an integer"),
    (AXES + "[params.refine]\nsplit = 1\n", "params.refine.split", "expected true or false"),
    (AXES + "[params.nope]\n", "params.nope", "not a known stage"),
    (AXES + "[settings]\ndevise = 'cpu'\n", "settings.devise", "did you mean 'device'"),
    ("[axes.scene.a]\n[axes.method.m]\ntrain = { iterations = 3 }\n", "axes.method.m.train",
     "runs per ('scene',), not per 'method'"),
    ("[axes.scene.a]\n[axes.method.m]\nrefine = { strenght = 3.0 }\n", "axes.method.m.refine",
     "did you mean 'strength'"),
    ("[axes.scene]\n", "axes.scene", "no values"),
    ("[axes.scene.'a/b']\n", "axes.scene", "may not"),
    # names become folder names (export, report): nothing that leaves or aliases a folder
    ("[axes.scene.'.']\n[axes.method.m]\n", "axes.scene", "may not"),
    ("[axes.scene.'..']\n[axes.method.m]\n", "axes.scene", "may not"),
    ("[axes.scene.a]\n[axes.method.'.hidden']\n", "axes.method", "start with a space or '.'"),
    ("[axes.scene.'a\\\\b']\n[axes.method.m]\n", "axes.scene", "may not"),
    ("[axes.scene.'a ']\n[axes.method.m]\n", "axes.scene", "end with a space"),
    ("[workflow]\nname = '../../elsewhere'\n" + AXES, "workflow.name", "names the report folder"),
    ("[workflow]\nname = '/tmp/abs'\n" + AXES, "workflow.name", "names the report folder"),
    ("[workflow]\nname = '..'\n" + AXES, "workflow.name", "names the report folder"),
    ("[axes.scene.a]\n", None, "no axis 'method'"),
    ("[workflow]\nstages = ['summry']\n", "workflow.stages", "did you mean 'summary'"),
    ("this is = not toml [", None, "invalid TOML"),
])
def test_schema_errors_name_the_file_and_key(tmp_path, text, key, message):
    path = write(tmp_path, text)
    with pytest.raises(WorkflowError) as info:
        load_workflow(path, toys.registry())
    text = str(info.value)
    assert str(path) in text and message in text
    if key:
        assert key in text


def test_settings_device_is_validated(tmp_path):
    path = write(tmp_path, toys.WORKFLOW.replace('device = "cpu"', 'device = "gpu"'))
    with pytest.raises(WorkflowError, match="device must be 'cpu', 'cuda'"):
        load_workflow(path, toys.registry())


@pytest.mark.parametrize("sets, message", [
    (["train.iterations"], "expected KEY=VALUE"),
    (["trian.iterations=3"], "did you mean 'train'"),
    (["train.iterations=lots"], "expected an integer"),
    (["train=3"], "expected STAGE.PARAM=VALUE"),
    (["train.nope=1"], "unknown param 'nope'"),
    (["device=tpu"], "device must be"),
])
def test_set_errors(toy, sets, message):
    with pytest.raises(WorkflowError, match=message) as info:
        toy.load(sets=sets)
    assert "--set" in str(info.value) or "settings" in str(info.value)


def test_env_vars_expand_and_fail_fast(tmp_path, monkeypatch):
    text = toys.WORKFLOW.replace('kind = "synthetic"\n\n[axes.scene.beta]',
                                 'kind = "${TOY_KIND}"\n\n[axes.scene.beta]')
    text = text.replace('[params.train]', '[params.load]\nsource = "${TOY_DATA:-data}/x"\n\n'
                                          '[params.train]')
    path = write(tmp_path, text)
    monkeypatch.delenv("TOY_KIND", raising=False)
    with pytest.raises(WorkflowError) as info:
        load_workflow(path, toys.registry())
    msg = str(info.value)
    assert "TOY_KIND is not set" in msg and "axes.scene.alpha.kind" in msg and str(path) in msg
    monkeypatch.setenv("TOY_KIND", "nvos")
    wf = load_workflow(path, toys.registry())
    plan = Plan(wf)
    assert plan.find("load", "alpha").item.attrs["scene"]["kind"] == "nvos"
    # Default used, then resolved relative to the workflow file's folder.
    assert plan.find("load", "alpha").params.value.source == tmp_path / "data" / "x"
    monkeypatch.setenv("TOY_DATA", "/abs/data")
    wf = load_workflow(path, toys.registry())
    assert Plan(wf).find("load", "alpha").params.value.source == Path("/abs/data/x")


def test_set_paths_resolve_against_cwd_and_file_paths_against_the_file(toy, tmp_path,
                                                                       monkeypatch):
    sub = tmp_path / "elsewhere"
    sub.mkdir()
    monkeypatch.chdir(sub)
    wf = toy.load(sets=["load.source=rel/dir"])
    assert Plan(wf).find("load", "beta").params.value.source == sub / "rel" / "dir"
    wf = toy.load(sets=["load.source=none"])
    assert Plan(wf).find("load", "beta").params.value.source is None


def test_set_can_edit_item_attributes(toy):
    wf = toy.load(sets=["axes.scene.alpha.kind=real", "axes.method.full.refine.strength=3"])
    plan = Plan(wf)
    assert plan.find("load", "alpha").item.attrs["scene"]["kind"] == "real"
    assert plan.find("refine", "beta/full").params.value.strength == 3.0
    assert plan.find("refine", "beta/nosplit").params.value.strength == 1.0


# -- richer params and axis schemas ---------------------------------------------------

@dataclass(frozen=True)
class Inner:
    delta: float = 0.5
    mode: Literal["released", "paper"] = "released"


@dataclass(frozen=True)
class RichParams:
    data: Path  # required: the workflow must set it
    sizes: tuple[int, ...] = (1, 2)
    weights: dict[str, float] = field(default_factory=dict)
    inner: Inner = Inner()
    label: Optional[str] = None


@dataclass(frozen=True)
class SceneAttrs:
    path: Path
    kind: str = "synthetic"
    title: str = field(default="", metadata={"cache_key": False})


def rich_registry():
    def run(ctx, inputs):
        return {}
    return Registry([Stage(name="rich", version=1, run=run, outputs=("r",), params=RichParams,
                           level=("scene",))], axis_schemas={"scene": SceneAttrs})


def test_typed_params_nested_dataclasses_and_schemas(tmp_path):
    path = write(tmp_path, """
[params.rich]
data = "inputs"
sizes = [4, 5, 6]
weights = { a = 1, b = 2.5 }
inner.mode = "paper"

[axes.scene.lego]
path = "../datasets/lego"
title = "Lego"
rich = { inner = { delta = 0.8 } }
""")
    wf = load_workflow(path, rich_registry(), sets=["rich.label=x", "rich.inner.delta=0.7"])
    task = Plan(wf).find("rich", "lego")
    p = task.params.value
    assert p.data == tmp_path / "inputs"
    assert p.sizes == (4, 5, 6) and p.weights == {"a": 1.0, "b": 2.5}
    assert p.inner == Inner(delta=0.7, mode="paper") and p.label == "x"
    attrs = task.item.attrs["scene"]
    assert isinstance(attrs, SceneAttrs)
    assert attrs.path == tmp_path.parent / "datasets" / "lego"
    assert wf.key_attrs(task.item) == {"scene": {"path": str(attrs.path), "kind": "synthetic"}}

    bad = path.read_text().replace('inner.mode = "paper"', 'inner.mode = "other"')
    path.write_text(bad)
    with pytest.raises(WorkflowError, match=r"params.rich.inner.mode.*one of \['released', "
                                            r"'paper'\]"):
        load_workflow(path, rich_registry())
    path.write_text("[axes.scene.lego]\npath = 'x'\ncolour = 1\n")
    with pytest.raises(WorkflowError, match="axes.scene.lego.colour"):
        load_workflow(path, rich_registry())
    path.write_text("[axes.scene.lego]\npath = 'x'\n")
    wf = load_workflow(path, rich_registry())
    with pytest.raises(WorkflowError, match="param 'data' .* has no default"):
        Plan(wf)


def test_nested_axis_values_are_declared_per_parent(tmp_path):
    def run(ctx, inputs):
        return {}
    reg = Registry([
        Stage(name="train", version=1, run=run, outputs=("scene",), level=("scene",)),
        Stage(name="seg", version=1, run=run, inputs=("scene",), outputs=("seg",),
              level=("scene", "object")),
        Stage(name="per_scene", version=1, run=run, inputs=("seg",), outputs=("ps",),
              level=("scene",)),
    ])
    path = write(tmp_path, """
[workflow]
nested = { object = "scene" }
[axes.scene.figurines]
[axes.scene.ramen]
[axes.object.figurines."green apple"]
[axes.object.figurines."rubber duck"]
[axes.object.ramen.egg]
""")
    plan = Plan(load_workflow(path, reg))
    assert [t.item.id for t in plan.tasks if t.stage.name == "seg"] == \
        ["figurines/green apple", "figurines/rubber duck", "ramen/egg"]
    ps = plan.find("per_scene", "figurines")
    assert ps.bindings[0].fan_in
    assert [plan.tasks[s].item.id for s in ps.bindings[0].sources] == \
        ["figurines/green apple", "figurines/rubber duck"]
    path.write_text(path.read_text().replace("[axes.object.ramen.egg]", "[axes.object.udon.egg]"))
    with pytest.raises(WorkflowError, match="'udon' is not a value of axis 'scene'"):
        load_workflow(path, reg)


def test_only_restricts_a_value_to_some_items(tmp_path):
    """A δ-sweep method on one scene and object: no task anywhere else, at any level; the
    other values' items are the plain product; a typo fails the load."""
    def run(ctx, inputs):
        return {}
    reg = Registry([
        Stage(name="train", version=1, run=run, outputs=("scene",), level=("scene",)),
        Stage(name="prep", version=1, run=run, inputs=("scene",), outputs=("prep",),
              level=("scene", "method")),
        Stage(name="seg", version=1, run=run, inputs=("prep",), outputs=("seg",),
              level=("scene", "method", "object")),
        Stage(name="per_method", version=1, run=run, inputs=("seg",), outputs=("pm",),
              level=("method",)),
        Stage(name="total", version=1, run=run, inputs=("seg",), outputs=("all",), level=()),
    ])
    text = """
[workflow]
nested = { object = "scene" }
[axes.scene.a]
[axes.scene.b]
[axes.scene.c]
[axes.method.m]
[axes.method.sweep]
only = "scene=a/object=x*"
[axes.object.a.x1]
[axes.object.a.x2]
[axes.object.a.y]
[axes.object.b.x1]
"""
    path = write(tmp_path, text)
    plan = Plan(load_workflow(path, reg))
    ids = lambda stage: [t.item.id for t in plan.tasks if t.stage.name == stage]  # noqa: E731
    assert ids("seg") == ["a/m/x1", "a/m/x2", "a/m/y", "a/sweep/x1", "a/sweep/x2", "b/m/x1"]
    assert ids("prep") == ["a/m", "a/sweep", "b/m", "c/m"]  # c has no object: its m item stays
    assert ids("per_method") == ["m", "sweep"]
    assert [plan.tasks[s].item.id for s in plan.find("total", "").bindings[0].sources] == ids("seg")
    assert [plan.tasks[s].item.id for s in plan.find("per_method", "sweep").bindings[0].sources] == \
        ["a/sweep/x1", "a/sweep/x2"]
    # a list of patterns; a nested value restricted by its sibling axis
    path.write_text(text.replace('only = "scene=a/object=x*"', 'only = ["scene=a/object=y", "scene=b"]')
                    + '[axes.object.b.z]\nonly = "method=m"\n')
    plan = Plan(load_workflow(path, reg))
    assert ids("seg") == ["a/m/x1", "a/m/x2", "a/m/y", "a/sweep/y", "b/m/x1", "b/m/z", "b/sweep/x1"]
    for bad, msg in (('"scene=a/object=nope"', "selects no item holding method 'sweep'"),
                     ('"a"', "names its axis"), ('"colour=red"', "unknown axis 'colour'"),
                     ("3", "expected an item pattern")):
        path.write_text(text.replace('"scene=a/object=x*"', bad))
        with pytest.raises(WorkflowError, match=msg) as err:
            load_workflow(path, reg)
        assert "axes.method.sweep.only" in str(err.value)


def test_item_equality_ignores_attributes():
    a = Item((("scene", "x"),), {"scene": {"k": 1}})
    b = Item((("scene", "x"),), {"scene": {"k": 2}})
    assert a == b and hash(a) == hash(b) and a.id == "x" and Item.root().label == "(workflow)"
    with pytest.raises(KeyError, match="no axis 'method'"):
        a["method"]
