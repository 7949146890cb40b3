"""tests/benchmarks/bm_seeds.py (issue 59 item 1: the baselines' own spread) and the two-level
bootstrap it pools the baselines with."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _bm_seeds():
    sys.path.insert(0, str(ROOT / "tests" / "benchmarks"))
    spec = importlib.util.spec_from_file_location("bm_seeds", ROOT / "tests" / "benchmarks" / "bm_seeds.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_the_pooled_interval_holds_the_baselines_spread():
    from cobgs.evaluate.protocols import bootstrap_across_baselines, bootstrap_mean_diff

    # three baselines: the same small view noise, but their own offsets (+1, +3, +5 points)
    views = [(0.5 + 0.001 * k, 0.5) for k in range(-5, 6)]

    def shifted(d):
        return {"a": [(x + d, y) for x, y in views], "b": [(x + d, y) for x, y in views]}

    pairs = {"s0t0": shifted(0.01), "s1t0": shifted(0.03), "s2t0": shifted(0.05)}
    pooled = bootstrap_across_baselines(pairs, reps=2000)
    assert pooled["baselines"] == 3 and pooled["diff"] == pytest.approx(3.0)
    assert pooled["per_baseline"] == pytest.approx({"s0t0": 1.0, "s1t0": 3.0, "s2t0": 5.0})
    one = bootstrap_mean_diff(pairs["s1t0"])
    # one baseline's interval covers its views only (about ±0.3); the pooled one the baselines' spread
    assert one["hi"] - one["lo"] < 1.0 < pooled["hi"] - pooled["lo"]
    assert pooled["lo"] <= 1.5 and pooled["hi"] >= 4.5
    assert bootstrap_across_baselines({"x": {}}) is None


def test_the_written_workflow_loads_and_shares_what_the_seeds_leave_equal(tmp_path, monkeypatch):
    from pipeline import Plan, load_workflow
    from stages.registry import load_registry

    bm = _bm_seeds()
    out = bm.write_workflow(ROOT / "workflows" / "synthetic_bench.toml", tmp_path / "seeds.toml")
    shared = Path(__file__).resolve().parents[2] / "shared" / "data"
    monkeypatch.setenv("COBGS_SHARED_DATA", str(shared))
    wf = load_workflow(out, load_registry())
    plan = Plan(wf)
    scenes = sorted({t.item["scene"] for t in plan.tasks if "scene" in t.item.axes})
    assert len(scenes) == 12 and "forward_coarse_s2t1" in scenes and "orbit_coarse" in scenes
    methods = sorted({t.item["method"] for t in plan.tasks if "method" in t.item.axes})
    assert methods == sorted(["ours_per_use", "ours_per_use_eq6", "raem_paper", "ngs_checked", "ngs", "flashsplat"])
    sfm = {t.item["scene"]: t.params.json for t in plan.tasks if t.stage.name == "sfm"}
    train = {t.item["scene"]: t.params.json for t in plan.tasks if t.stage.name == "train"}
    assert sfm["forward_coarse_s2t0"]["options"]["seed"] == 2 and sfm["forward_coarse_s0t1"]["options"]["seed"] == 0
    assert sfm["forward_coarse_s0t1"]["options"]["num_threads"] == 1  # the file's params, unchanged
    assert train["orbit_coarse_s1t1"]["seed"] == 1 and train["orbit_coarse_s1t0"]["seed"] == 0
    objs = {t.item["object"] for t in plan.tasks if t.stage.name == "refine" and t.item["scene"] == "orbit_coarse_s2t1"}
    assert "pole_noisy" in objs and "crate" in objs and len(objs) == 10


def test_a_smaller_design_writes_only_the_pairs_and_rows_asked(tmp_path, monkeypatch):
    from pipeline import Plan, load_workflow
    from stages.registry import load_registry

    bm = _bm_seeds()
    out = bm.write_workflow(ROOT / "workflows" / "synthetic_bench.toml", tmp_path / "seeds.toml",
                            pairs=[(0, 0), (1, 0), (2, 0), (0, 1)], rows=("ours_per_use", "raem_paper", "flashsplat"))
    monkeypatch.setenv("COBGS_SHARED_DATA", str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    plan = Plan(load_workflow(out, load_registry()))
    scenes = {t.item["scene"] for t in plan.tasks if "scene" in t.item.axes}
    assert scenes == {f"{s}{v}" for s in ("forward_coarse", "orbit_coarse") for v in ("", "_s1t0", "_s2t0", "_s0t1")}
    assert {t.item["method"] for t in plan.tasks if "method" in t.item.axes} == {"ours_per_use", "raem_paper", "flashsplat"}
    with pytest.raises(SystemExit, match="must hold"):
        bm.write_workflow(ROOT / "workflows" / "synthetic_bench.toml", tmp_path / "x.toml", pairs=[(1, 0)])
    with pytest.raises(SystemExit, match="S:T"):
        bm.main(["write", str(tmp_path / "y.toml"), "--pairs", "0:0,5:0"])
