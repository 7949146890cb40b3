"""Per-scene records at benchmark scale: exact- and noisy-mask objects are kept apart."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import pytest

from reports import ablation, methods, records
from reports.collect import Result, RunData, _oracle_results


def _res(scene, method, obj, biou, route, kind="cobgs"):
    return Result(scene=scene, method=method, object=obj,
                  row={"iou": biou, "acc": 0.99, "biou": biou, "mask_route": route, "method_kind": kind})


def test_scenes_mixing_mask_routes_get_one_row_per_route():
    results = [_res("s", "cobgs", "a", 0.9, "dataset masks"), _res("s", "cobgs", "b", 0.7, "dataset masks"),
               _res("s", "cobgs", "a_noisy", 0.5, "dataset masks + noise"),
               _res("t", "cobgs", "a", 0.8, "dataset masks")]
    data = RunData(workflow=None, cache_dir=Path("."), tasks=[], results=results, scenes={}, methods=["cobgs"])
    recs = records.scene_method_records(data, {}, lambda t: None)
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
    from reports.methods import MethodInfo

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
    recs, used = records.difference_records(data, infos, "cobgs")
    assert used == ["fs", "same"] and len(recs) == 1
    rec = recs[0]
    # means over views per object, then over objects: a 0.85 - 0.55, b 0.75 - 0.533..
    assert rec["d:fs"] == pytest.approx(100 * ((0.85 - 0.55) + (0.75 - 0.5333333333)) / 2)
    assert rec["_class"]["d:fs"] == ["better"] and "significantly above" in rec["_title"]["d:fs"]
    assert rec["d:same"] == 0 and rec["_text"]["d:same"] == "+0.00 [+0.00, +0.00]"


def _infos(ours: bool = False):
    from reports.methods import MethodInfo

    def cob(name, paper_sw, raem, options=(), role="variant", check="off"):
        return MethodInfo(name, kind="cobgs", options=list(options), role=role,
                          paper=("cobgs", paper_sw) if check == "off" else None, raem=raem,
                          switches=paper_sw + (check,))

    out = {"cobgs": cob("cobgs", (True, True, True), "released", role="reference"),
           "raem_paper": cob("raem_paper", (True, True, True), "paper", ["raem=paper"]),
           "no_raem": cob("no_raem", (True, True, False), "off", ["raem=off"]),
           "t5_bags": cob("t5_bags", (True, False, False), "off", ["bgtr=false", "raem=off"]),
           "nosplit": MethodInfo("nosplit", kind="nosplit", role="variant", paper=("nosplit",),
                                 switches=(False, False, False, "off")),
           "sa3d": MethodInfo("sa3d", kind="sa3d", paper=("sa3d",)),
           "delta_0.3": MethodInfo("delta_0.3", kind="cobgs", options=["delta=0.3"], role="variant")}
    if ours:
        out["cobgs"].role = "variant"
        out["ours"] = cob("ours", (True, True, True), "paper", ["raem=paper", "object_check=visible"],
                          role="reference", check="visible")
    return out


def _table_data(ours: bool = False):
    """Two scenes; scene s mixes exact and noisy masks. PSNR per object: vanilla 30."""
    psnr = {"cobgs": (29.5, 29.95), "raem_paper": (29.8, 29.95), "no_raem": (29.95, 29.95),
            "t5_bags": (29.0, 29.0), "nosplit": (30.0, 30.0), "sa3d": (30.0, 30.0), "delta_0.3": (29.9, 29.9)}
    biou = {"cobgs": 0.8, "raem_paper": 0.79, "no_raem": 0.78, "t5_bags": 0.75, "nosplit": 0.7, "sa3d": 0.72,
            "delta_0.3": 0.77}
    if ours:  # the checked variant of raem_paper: the same scene (PSNR), another foreground
        psnr["ours"], biou["ours"] = psnr["raem_paper"], 0.81
    results = []
    for scene, objects in (("s", (("a", "exact"), ("a_noisy", "noisy"))), ("t", (("b", "exact"),))):
        for obj, route in objects:
            for m, (after, before) in psnr.items():
                if m == "delta_0.3" and scene != "s":  # a sweep run on one scene only (`only`)
                    continue
                kind = "cobgs" if m not in ("nosplit", "sa3d") else m
                r = _res(scene, m, obj, biou[m] - (0.1 if route == "noisy" else 0), route, kind)
                r.row.update(psnr=after, psnr_before_raem=before, psnr_vanilla=30.0, psnr_delta=after - 30.0,
                             psnr_delta_before_raem=before - 30.0)
                r.per_view = {f"v{i}": {"biou": r.row["biou"] + 0.01 * i} for i in range(3)}
                results.append(r)
    return RunData(workflow=None, cache_dir=Path("."), tasks=[], results=results, scenes={n: SimpleNamespace(protocol="exact", dataset={}) for n in "st"},
                   methods=list(psnr))


def test_ablation_table_follows_the_paper_rows_per_scene_and_route():
    data, infos = _table_data(), _infos()
    by_scene = records.scene_method_records(data, infos, lambda t: None)
    recs = ablation.ablation_records(by_scene, infos)
    groups = list(dict.fromkeys((r["scene"], r["masks"]) for r in recs))
    assert groups == [("s", "exact"), ("s", "noisy"), ("t", None)]
    first = [r for r in recs if (r["scene"], r["masks"]) == ("s", "exact")]
    # the paper's order; the peer (sa3d) and the δ item are not ablation rows
    assert [r["method"] for r in first] == ["nosplit", "t5_bags", "no_raem", "cobgs", "raem_paper"]
    assert [(r["bags"], r["bgtr"], r["raem"]) for r in first] == [
        ("", "", "off"), ("✓", "", "off"), ("✓", "✓", "off"), ("✓", "✓", "released"), ("✓", "✓", "paper")]
    noisy = {r["method"]: r["biou"] for r in recs if r["masks"] == "noisy"}
    assert noisy["cobgs"] == pytest.approx(0.7) and noisy["nosplit"] == pytest.approx(0.6)
    # a workflow with one switch setting only has no ablation to show
    assert ablation.ablation_records([r for r in by_scene if r["method"] == "cobgs"], infos) == []


def test_psnr_table_is_table_4_with_the_scene_before_raem():
    data, infos = _table_data(), _infos()
    by_scene = records.scene_method_records(data, infos, lambda t: None)
    recs = {(r["scene"], r["masks"]): r for r in ablation.psnr_records(by_scene, infos, "cobgs")}
    assert set(recs) == {("s", "exact"), ("s", "noisy"), ("t", None)}
    r = recs[("t", None)]
    assert r["vanilla"] == 30.0 and r["mask_only"] == 29.0 and r["joint"] == 29.95
    assert r["raem_released"] == 29.5 and r["raem_paper"] == 29.8
    assert r["d_joint"] == pytest.approx(-0.05) and r["target"] == "met"
    # the bar is Table 4's: the scene before RAEM within 0.1 dB of vanilla
    for res in data.results:
        if res.method == "cobgs" and res.scene == "t":
            res.row["psnr_before_raem"] = 29.85
    by_scene = records.scene_method_records(data, infos, lambda t: None)
    r = {(x["scene"], x["masks"]): x for x in ablation.psnr_records(by_scene, infos, "cobgs")}[("t", None)]
    assert r["target"] == "not met" and r["_class"]["target"] == ["failed"]


def test_a_method_run_on_part_of_the_workflow_is_never_best_by_method():
    data, infos = _table_data(), _infos()
    recs = {r["method"]: r for r in records.method_records(data, infos, lambda t: None)[0]}
    assert recs["delta_0.3"]["_nobest"] and not recs["cobgs"]["_nobest"]
    assert recs["delta_0.3"]["_text"]["scenes"] == "1" and recs["cobgs"]["_text"]["scenes"] == "2"


def test_the_checked_variant_sits_beside_its_faithful_row():
    """docs/method.md §7: with the object-render check the reference is our variant: it is no
    paper row (no paper quotes), its ablation row says so, and its faithful twin (same switches
    and RAEM, check off) is compared with it like a peer."""
    from reports.paper import cobgs_switches, paper_method

    params = {"method": "cobgs", "cobgs": {"raem": "paper", "object_check": "visible"}}
    assert paper_method("cobgs", params) is None
    assert cobgs_switches("cobgs", params) == (True, True, True, "visible")
    assert paper_method("cobgs", {"method": "cobgs", "cobgs": {"raem": "paper"}}) == ("cobgs", (True, True, True))
    data, infos = _table_data(ours=True), _infos(ours=True)
    assert ablation.faithful_twins(infos, "ours") == ["raem_paper"]
    assert ablation.faithful_twins(infos, "cobgs") == []  # a faithful reference has no twin
    by_scene = records.scene_method_records(data, infos, lambda t: None)
    first = [r for r in ablation.ablation_records(by_scene, infos) if (r["scene"], r["masks"]) == ("s", "exact")]
    assert [(r["method"], r["check"]) for r in first][-2:] == [("raem_paper", ""), ("ours", "visible")]
    # issue 58: the twin and the role are written once, by the report (bm_segmentation.py reads them)
    assert [(r["method"], r["twin"], r["role"]) for r in first][-2:] == [("raem_paper", "", "variant"),
                                                                          ("ours", "raem_paper", "reference")]
    recs, used = records.difference_records(data, infos, "ours")
    assert "raem_paper" in used and "cobgs" not in used and "no_raem" not in used
    rec = next(r for r in recs if r["scene"] == "t")
    assert rec["d:raem_paper"] == pytest.approx(2.0)
    psnr = {(r["scene"], r["masks"]): r for r in ablation.psnr_records(by_scene, infos, "ours")}
    assert psnr[("t", None)]["raem_paper"] == 29.8  # the check leaves the scene as it was


def test_params_recorded_before_the_object_check_existed_read_as_off():
    """Entries written before `cobgs.object_check` existed ran without it and share the key of
    "off" (stages/refine.py): the report reads them so, so that a method's old and new entries
    do not look like per-scene overrides."""
    from reports.collect import _with_later_params

    defaults = {"cobgs": {"object_check": "visible", "raem": "paper"}}
    assert _with_later_params({"cobgs": {"raem": "paper"}}, defaults)["cobgs"]["object_check"] == "off"
    assert _with_later_params({"cobgs": {"object_check": "visible"}}, defaults)["cobgs"]["object_check"] == "visible"
    # a refine stage that has no such param (another program's) is left alone
    assert "object_check" not in _with_later_params({"cobgs": {}}, {"cobgs": {}})["cobgs"]


def test_ngs_rows_join_table_5_as_cobgs_plus_its_stage():
    """Issue 48: NG-GS's rows sit in the Table 5 section as the switches of the COB-GS they run
    plus an 'Added stage' column; they are peers, never the checked row's faithful twin, and
    never Table 4's RAEM column (that is COB-GS's scene)."""
    wf = SimpleNamespace(graph=SimpleNamespace(producer={}))
    params = {
        "cobgs": {"method": "cobgs", "cobgs": {"raem": "released", "object_check": "off"}},
        "raem_paper": {"method": "cobgs", "cobgs": {"raem": "paper", "object_check": "off"}},
        "ours": {"method": "cobgs", "cobgs": {"raem": "paper", "object_check": "visible"}},
        "no_raem": {"method": "cobgs", "cobgs": {"raem": "off", "object_check": "off"}},
        "ngs": {"method": "ngs", "cobgs": {"raem": "released", "object_check": "off"}, "ngs": {}},
        "ngs_checked": {"method": "ngs", "cobgs": {"raem": "paper", "object_check": "visible"}, "ngs": {}},
    }
    psnr = {"cobgs": 29.5, "raem_paper": 29.8, "ours": 29.8, "no_raem": 29.9, "ngs": 28.0, "ngs_checked": 28.5}
    results = []
    for m, p in params.items():
        r = _res("s", m, "a", 0.8, "dataset masks", p["method"])
        r.refine_params = p
        r.row.update(psnr=psnr[m], psnr_before_raem=29.95, psnr_vanilla=30.0, psnr_delta=psnr[m] - 30.0)
        results.append(r)
    from reports.collect import SceneRecord

    data = RunData(workflow=wf, cache_dir=Path("."), tasks=[], results=results,
                   scenes={"s": SceneRecord("s", dataset={"protocol": "exact"})}, methods=list(params))
    infos = methods.method_infos(data)
    assert infos["ngs"].stage == "NG-GS" and infos["cobgs"].stage == ""
    assert infos["ngs"].switches == (True, True, True, "off") and infos["ngs"].raem == "released"
    assert infos["ngs_checked"].switches == (True, True, True, "visible") and infos["ngs_checked"].raem == "paper"
    assert infos["ngs"].paper is None and infos["ngs"].role == "peer"
    assert ablation.faithful_twins(infos, "ours") == ["raem_paper"]
    by_scene = records.scene_method_records(data, infos, lambda t: None)
    recs = ablation.ablation_records(by_scene, infos)
    assert [(r["method"], r["raem"], r["check"], r["stage"]) for r in recs] == [
        ("no_raem", "off", "", ""), ("cobgs", "released", "", ""), ("ngs", "released", "", "NG-GS"),
        ("raem_paper", "paper", "", ""), ("ours", "paper", "visible", ""), ("ngs_checked", "paper", "visible", "NG-GS")]
    table4 = ablation.psnr_records(by_scene, infos, "ours")[0]
    assert table4["raem_released"] == 29.5 and table4["raem_paper"] == 29.8  # not NG-GS's 28.0 / 28.5

    from reports.sections import result_tables
    from reports.tables import to_markdown

    md = to_markdown(result_tables(data, infos, lambda t: None)["ablation"])
    assert "| Added stage |" in md and "| ngs (NG-GS · " in md and "| NG-GS |" in md
