"""Per-scene records at benchmark scale: exact- and noisy-mask objects are kept apart."""

from __future__ import annotations

from pathlib import Path

import pytest

from reports import results as R
from reports.collect import Result, RunData, _oracle_results


def _res(scene, method, obj, biou, route, kind="cobgs"):
    return Result(scene=scene, method=method, object=obj,
                  row={"iou": biou, "acc": 0.99, "biou": biou, "mask_route": route, "method_kind": kind})


def test_scenes_mixing_mask_routes_get_one_row_per_route():
    results = [_res("s", "cobgs", "a", 0.9, "dataset masks"), _res("s", "cobgs", "b", 0.7, "dataset masks"),
               _res("s", "cobgs", "a_noisy", 0.5, "dataset masks + noise"),
               _res("t", "cobgs", "a", 0.8, "dataset masks")]
    data = RunData(workflow=None, cache_dir=Path("."), tasks=[], results=results, scenes={}, methods=["cobgs"])
    recs = R.scene_method_records(data, {}, lambda t: None)
    by = {(r["scene"], r["masks"]): r for r in recs}
    assert set(by) == {("s", "dataset masks"), ("s", "dataset masks + noise"), ("t", None)}
    assert by[("s", "dataset masks")]["biou"] == pytest.approx(0.8)
    assert by[("s", "dataset masks + noise")]["biou"] == pytest.approx(0.5)
    assert len({r["_group"] for r in recs}) == 3  # best values marked within each


def test_flashsplat_oracle_copies_the_best_bias_per_scene():
    results = [_res("s", "fs0", "a", 0.6, "m", "flashsplat"), _res("s", "fs0", "b", 0.6, "m", "flashsplat"),
               _res("s", "fs1", "a", 0.9, "m", "flashsplat"), _res("s", "fs1", "b", 0.2, "m", "flashsplat"),
               _res("t", "fs0", "a", 0.1, "m", "flashsplat"), _res("t", "fs1", "a", 0.3, "m", "flashsplat"),
               _res("s", "cobgs", "a", 0.99, "m")]
    for r in results:
        r.refine_params = {"method": r.row["method_kind"]}
    out = _oracle_results(results)
    # s: fs0 0.60 vs fs1 0.55 mean over objects -> fs0; t: fs1
    assert {(r.scene, r.object, r.row["oracle_choice"]) for r in out} == {("s", "a", "fs0"), ("s", "b", "fs0"),
                                                                         ("t", "a", "fs1")}
    assert all(r.method == "flashsplat_oracle" for r in out)
    # one FlashSplat item only: no sweep, no oracle
    assert _oracle_results([r for r in results if r.method != "fs1"]) == []


def test_difference_to_each_peer_with_a_view_bootstrap_interval():
    from reports.results import MethodInfo

    def res(method, obj, vals, kind):
        r = _res("s", method, obj, sum(vals) / len(vals), "m", kind)
        r.per_view = {f"v{i}": {"biou": v} for i, v in enumerate(vals)}
        return r

    results = [res("cobgs", "a", [0.9, 0.8, 0.85], "cobgs"), res("cobgs", "b", [0.7, 0.75, 0.8], "cobgs"),
               res("fs", "a", [0.6, 0.5, 0.55], "flashsplat"), res("fs", "b", [0.5, 0.5, 0.6], "flashsplat"),
               res("same", "a", [0.9, 0.8, 0.85], "sa3d"), res("same", "b", [0.7, 0.75, 0.8], "sa3d")]
    data = RunData(workflow=None, cache_dir=Path("."), tasks=[], results=results, scenes={},
                   methods=["cobgs", "fs", "same"])
    infos = {"cobgs": MethodInfo("cobgs", kind="cobgs", role="reference"),
             "fs": MethodInfo("fs", kind="flashsplat"), "same": MethodInfo("same", kind="sa3d")}
    recs, used = R.difference_records(data, infos, "cobgs")
    assert used == ["fs", "same"] and len(recs) == 1
    rec = recs[0]
    # means over views per object, then over objects: a 0.85 - 0.55, b 0.75 - 0.533..
    assert rec["d:fs"] == pytest.approx(100 * ((0.85 - 0.55) + (0.75 - 0.5333333333)) / 2)
    assert rec["_class"]["d:fs"] == ["better"] and "significantly above" in rec["_title"]["d:fs"]
    assert rec["d:same"] == 0 and rec["_text"]["d:same"] == "+0.00 [+0.00, +0.00]"
