"""Stage declarations and the DAG: validation errors and ordering."""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from pipeline import (CycleError, DuplicateOutputError, Graph, MissingInputError, Registry,
                      Resources, Settings, Stage, StageSpecError)


def noop(ctx, inputs):
    return {}


def stage(name, inputs=(), outputs=None, **kw):
    return Stage(name=name, version=1, run=noop, inputs=inputs,
                 outputs=outputs if outputs is not None else (f"{name}_out",), **kw)


@dataclass
class Mutable:
    x: int = 1


@dataclass(frozen=True)
class Frozen:
    x: int = 1


@pytest.mark.parametrize("kwargs, message", [
    ({"name": "Bad-Name"}, "stage name must match"),
    ({"name": "all"}, "reserved"),
    ({"version": ""}, "version must be"),
    ({"version": True}, "version must be"),
    ({"run": 3}, "run must be callable"),
    ({"outputs": ()}, "declares no outputs"),
    ({"outputs": "a"}, "must be a tuple"),
    ({"inputs": ("a", "a")}, "more than once"),
    ({"inputs": ("a",), "outputs": ("a",)}, "both inputs and outputs"),
    ({"params": Mutable}, "must be frozen"),
    ({"params": dict}, "must be a dataclass"),
    ({"resources": "2 gpus"}, "resources must be"),
])
def test_stage_declaration_errors(kwargs, message):
    spec = dict(name="s", version=1, run=noop, outputs=("o",))
    spec.update(kwargs)
    with pytest.raises(StageSpecError, match=message):
        Stage(**spec)


def test_resources_follow_device():
    gpu = stage("g", uses_device=True, resources=Resources(cpus=2))
    assert gpu.resources_for(Settings("cuda")).gpus == 1.0
    assert gpu.resources_for(Settings("cpu")).gpus == 0.0
    assert gpu.resources_for(Settings("cpu")).cpus == 2
    dyn = stage("d", uses_device=True,
                resources=lambda s: Resources(cpus=4 if s.device == "cpu" else 1, gpus=0.5))
    assert dyn.resources_for(Settings("cuda:1")) == Resources(cpus=1, gpus=0.5)
    assert dyn.resources_for(Settings("cpu")) == Resources(cpus=4, gpus=0)
    with pytest.raises(StageSpecError):
        Resources(cpus=-1)


def test_order_follows_artifacts_not_declaration():
    # Declared backwards on purpose: the order must come from the artifact names.
    g = Graph([stage("report", inputs=("metrics",)),
               stage("evaluate", inputs=("refined", "scene"), outputs=("metrics",)),
               stage("refine", inputs=("scene",), outputs=("refined",)),
               stage("train", outputs=("scene",)),
               stage("unrelated")])
    order = list(g.order)
    assert order.index("train") < order.index("refine") < order.index("evaluate") \
        < order.index("report")
    assert g.upstream["evaluate"] == ("refine", "train")
    assert g.ancestors(["refine"]) == {"refine", "train"}
    assert g.descendants(["refine"]) == {"refine", "evaluate", "report"}
    assert set(g.subgraph(["evaluate"]).order) == {"train", "refine", "evaluate"}


def test_cycle_is_reported_by_stage_names():
    with pytest.raises(CycleError) as info:
        Graph([stage("a", inputs=("c_out",)), stage("b", inputs=("a_out",)),
               stage("c", inputs=("b_out",)), stage("d")])
    cycle = info.value.cycle
    assert set(cycle) == {"a", "b", "c"} and cycle[0] == cycle[-1]
    # Data flows along the reported cycle: each stage produces what the next consumes.
    producers = {"a": "a_out", "b": "b_out", "c": "c_out"}
    consumes = {"a": "c_out", "b": "a_out", "c": "b_out"}
    for up, down in zip(cycle, cycle[1:]):
        assert consumes[down] == producers[up]
    assert " -> ".join(cycle) in str(info.value)


def test_duplicate_output_names_both_stages():
    with pytest.raises(DuplicateOutputError, match="'train'.*'train2'"):
        Graph([stage("train", outputs=("scene",)), stage("train2", outputs=("scene",))])
    with pytest.raises(DuplicateOutputError, match="declared twice"):
        Graph([stage("a"), stage("a")])


def test_missing_input_is_rejected_with_a_hint():
    with pytest.raises(MissingInputError, match=r"'refine' needs artifact 'scenes'.*did you "
                                                r"mean 'scene'"):
        Graph([stage("train", outputs=("scene",)), stage("refine", inputs=("scenes",))])


def test_registry_rejects_double_registration_and_validates_lazily():
    a = stage("a")
    reg = Registry([a])
    reg.add(a)  # the same object twice is harmless (re-imported module)
    with pytest.raises(StageSpecError, match="registered twice"):
        reg.add(stage("a"))
    reg.add(stage("b", inputs=("nothing",)))
    with pytest.raises(MissingInputError):
        reg.graph()
    assert Registry().graph().order == ()
