"""The builder on a recorded run (no browser): numbers as measured, failures with their
logs, gaps shown as gaps, quoted paper numbers labelled, a self-contained folder written
atomically, and the ``cobgs report`` command."""

from __future__ import annotations

import json
import re
from html.parser import HTMLParser
from pathlib import Path

import pytest

from reports.errors import ReportError
from reports.builder import MARKER


class Links(HTMLParser):
    """Every src / href of a page, and the text of each table cell by (table id, row)."""

    def __init__(self):
        super().__init__()
        self.urls: list[str] = []
        self.rows: dict[str, list[list[tuple[str, dict]]]] = {}
        self._table = None
        self._row = None
        self._cell = None
        self._in_sub = False  # the small second line of a cell (method options) is not its text

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "span" and a.get("class") == "sub":
            self._in_sub = True
        for k in ("src", "href"):
            if a.get(k) is not None:
                self.urls.append(a[k])
        if tag == "table":
            self._table = a.get("id") or "_"  # tables without an id share "_"
        elif tag == "tr" and self._table:
            self._row = []
        elif tag == "td" and self._row is not None:
            self._cell = ["", a]

    def handle_data(self, data):
        if self._cell is not None and not self._in_sub:
            self._cell[0] += data

    def handle_endtag(self, tag):
        if tag == "span":
            self._in_sub = False
        if tag == "td" and self._cell is not None:
            self._row.append((self._cell[0].strip(), self._cell[1]))
            self._cell = None
        elif tag == "tr" and self._row is not None:
            if self._row:
                self.rows.setdefault(self._table, []).append(self._row)
            self._row = None
        elif tag == "table":
            self._table = None


def parse(index: Path) -> Links:
    p = Links()
    p.feed(index.read_text(encoding="utf-8"))
    return p


def metrics_rows(recorded) -> list[dict]:
    rows = []
    for f in sorted((recorded.cache / "entries" / "evaluate").glob("*/out/metrics.json")):
        rows.append(json.loads(f.read_text())["row"])
    return rows


def test_method_means_are_the_measured_ones(recorded, report):
    """mIoU per method = mean over scenes of the mean over objects of evaluate's rows."""
    rows = metrics_rows(recorded)
    assert len(rows) == 13  # 15 items, two refines failed
    record = json.loads((report.parent / MARKER).read_text())
    by_method = {r["method"]: r for r in record["by_method"]}
    for method in ("cobgs", "no_bgtr", "nosplit", "flashsplat"):
        scene_means = []
        for scene in ("s1", "s2"):
            ious = [r["iou"] for r in rows if r["method"] == method and r["scene"] == scene]
            if ious:
                scene_means.append(sum(ious) / len(ious))
        assert by_method[method]["iou"] == pytest.approx(sum(scene_means) / len(scene_means), abs=1e-12)
    assert by_method["flashsplat"]["scenes"] == 1  # s2 has no result: not averaged in as zero
    assert by_method["nosplit"]["scenes"] == 2 and by_method["nosplit"]["objects"] == 2


def test_summary_table_marks_best_and_shows_percentages(report):
    rows = parse(report).rows["t-method"]
    methods = [r[0][0] for r in rows]
    assert methods == ["cobgs", "no_bgtr", "delta_03", "nosplit", "flashsplat"]
    miou = [r[3] for r in rows]  # Method, Scenes, Objects, mIoU, ...
    assert "best" in miou[0][1]["class"] and float(miou[0][0]) == max(float(c[0]) for c in miou)
    assert not any("best" in c[1].get("class", "") for c in miou[1:])
    # incomplete methods never take a best mark and say why: a scene missing (flashsplat),
    # or every scene but not every object (nosplit, whose mean covers fewer objects)
    cols = [c[0] for c in rows[-1]]
    assert cols[1:3] == ["1 of 2", "2 of 3"] and "failed: refine" in cols[-1]
    nosplit = [c[0] for c in rows[3]]
    assert nosplit[1:3] == ["2", "2 of 3"] and "failed: refine" in nosplit[-1]
    assert not any("best" in c[1].get("class", "") for r in rows[3:] for c in r)


def test_failure_is_listed_with_its_log_copied_into_the_report(report):
    html = report.read_text(encoding="utf-8")
    assert "simulated failure of s2/flashsplat/ball" in html
    logs = [u for u in parse(report).urls if u.startswith("logs/") and "-failed" in u]
    assert logs, "no link to the failure log"
    text = (report.parent / logs[0]).read_text()
    assert "about to fail on purpose" in text and "RuntimeError" in text


def test_gaps_show_as_gaps_not_numbers(report):
    p = parse(report)
    obj_rows = {(r[0][0], r[1][0], r[2][0]): r for r in p.rows["t-object"]}
    failed = obj_rows[("s2", "flashsplat", "ball")]
    assert [c[0] for c in failed[3:6]] == ["", "", ""]  # IoU, Acc, BIoU: empty, not 0
    assert "failed: refine" in failed[-1][0]
    html = report.read_text(encoding="utf-8")
    assert "waits on refine[s2/flashsplat/ball]" in html
    gaps = parse(report).rows["_"]
    assert ["s1", "box", "1", "1× empty GT", "v004"] in [[c[0] for c in r] for r in gaps]
    assert "failed at refine" in html  # its row in the picture grid


def test_report_is_self_contained(report):
    root = report.parent
    urls = parse(report).urls
    assert urls
    for u in urls:
        if u.startswith("#"):
            continue
        assert not re.match(r"^[a-z]+:", u) and not u.startswith("/"), f"non-relative link {u}"
        assert (root / u).is_file(), f"dangling link {u}"
    for f in list(root.rglob("*.html")) + list(root.rglob("*.css")) + list(root.rglob("*.js")) + \
            list(root.rglob("*.svg")):
        text = f.read_text(encoding="utf-8")
        # SVGs name their XML namespaces with http URLs; nothing may be *loaded* from one
        text = re.sub(r'xmlns(:\w+)?="http[^"]*"', "", text)
        text = re.sub(r'<!DOCTYPE[^>]*>', "", text)
        assert not re.search(r"(src|href|url)\s*[=(]\s*[\"']?(https?:)?//", text), f"remote reference in {f}"


def test_pictures_and_plots_exist(report):
    root = report.parent
    for name in ("iou_biou", "psnr", "time", "delta_sweep", "scores"):
        assert (root / "plots" / f"{name}.svg").stat().st_size > 1000
    for method in ("cobgs", "no_bgtr", "delta_03", "nosplit", "flashsplat"):
        for kind in ("pred.png", "overlay.png", "crop.png", "object.jpg", "removed.jpg"):
            assert (root / "img" / "s1" / "ball" / "v000" / method / kind).is_file()
    assert (root / "img" / "s1" / "ball" / "v000" / "gt.png").is_file()
    assert not (root / "img" / "s2" / "ball" / "v000" / "flashsplat").exists()  # failed: nothing drawn


def test_overlay_counts_agree_with_the_evaluate_stage(recorded, report):
    """FP / FN pixels under each picture are those evaluate counted on that view (from the
    mask it scored: the visible one here, not the object-only render)."""
    html = report.read_text(encoding="utf-8")
    per = {}
    for f in (recorded.cache / "entries" / "evaluate").glob("*/out/metrics.json"):
        m = json.loads(f.read_text())
        r = m["row"]
        per[(r["scene"], r["method"], r["object"])] = m["details"]["per_view"]["v000"]
    section = html[html.index('id="pic-s1_ball'):]
    section = section[:section.index("</article>")]
    for method in ("cobgs", "no_bgtr", "nosplit"):
        s = per[("s1", method, "ball")]
        row = section[section.index(f'<span class="mname">{method}</span>'):]
        m = re.search(r"FP ([\d\u2009]+) px · FN ([\d\u2009]+) px", row)
        assert (int(m.group(1).replace("\u2009", "")), int(m.group(2).replace("\u2009", ""))) == (s["fp"], s["fn"])


def test_paper_numbers_appear_only_where_the_protocol_and_method_match(tmp_path_factory):
    from report_fixture_run import Recorded

    rec = Recorded(tmp_path_factory.mktemp("nvos"), protocol="nvos", fail_on="", scenes=("fern", "trex"))
    index = rec.build(tmp_path_factory.mktemp("nvos_report") / "r")
    record = json.loads((index.parent / MARKER).read_text())
    by = {r["method"]: r for r in record["by_method"]}
    assert by["cobgs"]["paper_iou"] == pytest.approx(0.921) and by["cobgs"]["paper_acc"] == pytest.approx(0.986)
    assert by["nosplit"]["paper_iou"] == pytest.approx(0.912)  # paper Table 5, first row
    assert by["flashsplat"]["paper_iou"] == pytest.approx(0.918)
    assert "paper_iou" not in by["delta_03"] and "paper_iou" not in by["no_bgtr"]
    p = parse(index)
    heads = index.read_text(encoding="utf-8")
    assert "paper mIoU †" in heads and "quoted from the paper" in heads
    cobgs = next(r for r in p.rows["t-method"] if r[0][0] == "cobgs")
    quoted = [c for c in cobgs if "quoted" in c[1].get("class", "")]
    assert [c[0] for c in quoted] == ["92.1", "98.6"]
    assert all("best" not in c[1]["class"] for c in quoted)
    assert all("partial" in c[1]["class"] for c in quoted)  # 2 of the 8 NVOS tasks
    assert "covers 2 of the 8 tasks" in quoted[0][1]["title"]
    # per scene: Table 4 PSNR for COB-GS (joint) and the mask-only row
    scene_rows = {(r[0][0], r[1][0]): r for r in p.rows["t-scene"]}
    assert any(c[0] == "24.29 (24.26)" for c in scene_rows[("fern", "cobgs")])
    assert any(c[0] == "23.35 (24.68)" for c in scene_rows[("trex", "no_bgtr")])


def test_exact_protocol_has_no_paper_columns(report):
    assert "paper mIoU" not in report.read_text(encoding="utf-8")


def test_rebuild_replaces_an_old_report_atomically(recorded, report, tmp_path, monkeypatch):
    import shutil

    import reports.builder as B

    out = tmp_path / "r"
    shutil.copytree(report.parent, out)
    (out / "stale.txt").write_text("from an older report")
    with pytest.raises(ReportError, match=r"also holds files .*\['stale.txt'\].*--replace"):
        recorded.build(out)  # a file the report did not write: the user's, kept (issue 44 H1)
    recorded.build(out, replace=True)
    assert not (out / "stale.txt").exists() and (out / "index.html").is_file()

    def crash(*a, **k):  # dies after tables and pictures are written, before the page
        raise RuntimeError("disk full (simulated)")

    monkeypatch.setattr(B, "_plots", crash)
    before = (out / "index.html").read_bytes()
    with pytest.raises(RuntimeError, match="simulated"):
        recorded.build(out)
    assert (out / "index.html").read_bytes() == before  # the old report is untouched
    assert [p.name for p in tmp_path.iterdir()] == ["r"]  # no temporary folder left behind


def test_refuses_to_replace_a_folder_that_is_not_a_report(recorded, tmp_path):
    out = tmp_path / "precious"
    out.mkdir()
    (out / "thesis.tex").write_text("x")
    with pytest.raises(ReportError, match="did not write"):
        recorded.build(out)
    assert (out / "thesis.tex").read_text() == "x"


def test_leftovers_of_a_killed_report_are_cleaned(recorded, tmp_path):
    """A SIGKILLed `cobgs report` leaves .NAME.tmp-PID / .NAME.old-PID folders; the next
    report to that destination removes them (their pid is dead) and puts back a previous
    report that a kill left renamed away."""
    import os

    out = tmp_path / "r"
    recorded.build(out)
    dead = 2 ** 22 + 1  # above the default pid_max: no such process
    (tmp_path / f".r.tmp-{dead}").mkdir()
    os.rename(out, tmp_path / f".r.old-{dead}")
    (tmp_path / f".r.old-{os.getpid()}x").mkdir()  # not a leftover name: kept
    recorded.build(out)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["r", f".r.old-{os.getpid()}x"])
    assert (out / "index.html").is_file()


def test_missing_cache_is_a_clear_error(recorded, tmp_path):
    from stages.commands.report import build_report

    with pytest.raises(ReportError, match="cache folder .* does not exist"):
        build_report(recorded.workflow, out_dir=tmp_path / "r", cache_dir=tmp_path / "nope",
                     registry=recorded.registry)


def test_never_run_workflow_reports_missing_everything(recorded, tmp_path):
    (tmp_path / "cache").mkdir()
    from stages.commands.report import build_report

    index = build_report(recorded.workflow, out_dir=tmp_path / "r", cache_dir=tmp_path / "cache",
                         registry=recorded.registry)
    html = index.read_text(encoding="utf-8")
    assert "nothing has run yet" in html and "0 of 0" not in html
    record = json.loads((index.parent / MARKER).read_text())
    assert record["counts"] == {"missing": 50} or set(record["counts"]) == {"missing"}


def test_cli(recorded, tmp_path, monkeypatch, capsys):
    from stages.commands.cli import main

    monkeypatch.setenv("COBGS_BUILTIN_STAGES", "0")
    monkeypatch.setenv("COBGS_STAGE_MODULES", "report_fixture_run")
    out = tmp_path / "cli"
    rc = main(["report", str(recorded.workflow), "--cache-dir", str(recorded.cache), "--out", str(out)])
    assert rc == 0 and (out / "index.html").is_file()
    assert f"file://{(out / 'index.html').resolve()}" in capsys.readouterr().out
    rc = main(["report", str(recorded.workflow), "--cache-dir", str(tmp_path / "absent"), "--out", str(out)])
    assert rc == 2 and "does not exist" in capsys.readouterr().err
    rc = main(["report", str(recorded.workflow), "--cache-dir", str(recorded.cache), "--set", "refine.nope=1"])
    assert rc == 2 and "nope" in capsys.readouterr().err


def test_delta_sweep_points_are_the_recorded_counts(recorded):
    """Fig. 7's points: each run's own ambiguous count and size from refine.json, and the
    fixed-δ count recomputed from its last mask stage's scores."""
    import numpy as np

    from pipeline import load_workflow
    from reports.collect import collect
    from reports.methods import method_infos
    from reports.plotdata import FIXED_DELTA, delta_groups

    data = collect(load_workflow(recorded.workflow, recorded.registry, []), recorded.cache)
    groups = dict(delta_groups(data, method_infos(data)))
    assert set(groups) == {"s1 / ball", "s1 / box", "s2 / ball"}  # cobgs (δ 0.5) + delta_03
    for r in data.results:
        if r.method not in ("cobgs", "delta_03") or not r.ok:
            continue
        pts = {p[0]: p for p in groups[f"{r.scene} / {r.object}"]}
        d, own, total, fixed = pts[r.refine["delta"]]
        with np.load(r.refine_dir / "stage_scores.npz") as z:
            last = z[f"stage_{len(z.files) - 1}"]
        assert (own, total) == (r.refine["ambiguous_final"], r.refine["num_gaussians_end"])
        assert fixed == np.count_nonzero(last < FIXED_DELTA)


def test_metadata_lists_the_dependency_versions_the_tasks_recorded(recorded, report):
    from importlib import metadata

    recorded_versions = {}
    for f in (recorded.cache / "entries").glob("*/*/manifest.json"):
        recorded_versions.update(json.loads(f.read_text()).get("dependencies", {}))
    assert recorded_versions.get("pytest") == metadata.version("pytest")
    html = report.read_text(encoding="utf-8")
    section = html.split("Dependency versions the run used", 1)[1].split("Package versions at report time", 1)[0]
    assert 'class="data plain versions run-deps"' in section
    assert f"<code>pytest</code></td><td>{metadata.version('pytest')}</td>" in section


def test_gpu_peak_column_only_when_tasks_recorded_one(recorded, report, tmp_path):
    import shutil

    from stages.commands.report import build_report

    assert "Peak GPU" not in report.read_text(encoding="utf-8")  # a CPU run: no empty column
    cache = tmp_path / "cache"
    shutil.copytree(recorded.cache, cache)
    for f in (cache / "entries" / "refine").glob("*/manifest.json"):
        m = json.loads(f.read_text())
        m["gpu_peak_bytes"] = 3 << 30
        f.write_text(json.dumps(m))
    index = build_report(recorded.workflow, out_dir=tmp_path / "r", cache_dir=cache, registry=recorded.registry)
    rows = parse(index).rows
    html = index.read_text(encoding="utf-8")
    assert html.count(">Peak GPU<") >= 3  # by method, by scene, per object, tasks
    assert any(cell == "3.0 GiB" for row in rows["t-method"] for cell, _ in row)


def test_every_column_is_defined_on_the_page(recorded, tmp_path):
    """Each table header carries its definition (tooltip) and each table lists its columns'
    definitions under it: a reader never meets an unexplained mBIoU or ΔPSNR."""
    import re

    html = recorded.build(tmp_path / "r").read_text()
    tables = re.findall(r'<table id="[^"]*" class="data.*?</thead>', html, re.S)
    headers = [h for t in tables for h in re.findall(r"<th scope=\"col\"[^>]*>", t)]
    assert headers and all('title="' in h for h in headers), [h for h in headers if 'title="' not in h][:5]
    assert html.count('<details class="columns">') >= html.count("<table id=") > 0
    assert "<dt>mBIoU</dt>" in html or "<dt>BIoU</dt>" in html


def test_ablation_and_psnr_tables_and_their_markdown(recorded, report):
    """Paper Table 5's rows in the paper's order (no-split = none, then BAGS + RAEM without
    BGTR, then all three), Table 4's columns, and tables.md with the page's numbers."""
    rows = parse(report).rows
    abl = [[c[0] for c in r] for r in rows["t-ablation"]]
    s1 = [r for r in abl if r[0] == "s1"]
    assert [r[1] for r in s1] == ["nosplit", "no_bgtr", "cobgs"]  # delta_03 (not the paper's δ) and peers left out
    assert [tuple(r[2:5]) for r in s1] == [("", "", "off"), ("✓", "", "released"), ("✓", "✓", "released")]
    by_scene = {(r[0][0], r[1][0]): r for r in rows["t-scene"]}  # Scene, Method, Objects, mIoU, ...
    cobgs_s1 = [r for r in rows["t-ablation"] if r[0][0] == "s1" and r[1][0] == "cobgs"][0]
    assert cobgs_s1[5][0] == by_scene[("s1", "cobgs")][3][0]  # mIoU: the same number as the results table
    psnr = {r[0][0]: [c[0] for c in r] for r in rows["t-psnr"]}
    assert set(psnr) == {"s1", "s2"} and psnr["s1"][-1] in ("met", "not met")
    md = (report.parent / "tables.md").read_text()
    assert "| Scene | Method | BAGS | BGTR | RAEM |" in md and "Texture quality (paper Table 4)" in md
    assert "Added stage" not in md  # no row here adds a stage to COB-GS's (NG-GS would)
    assert f"| {by_scene[('s1', 'cobgs')][3][0]} |" in md or f"**{by_scene[('s1', 'cobgs')][3][0]}**" in md
    assert (report.parent / "data" / "ablation.csv").is_file() and (report.parent / "data" / "texture_psnr.csv").is_file()
    # the method data/differences.csv is taken against (bm_segmentation.py reads it there)
    assert json.loads((report.parent / "report.json").read_text())["reference"] == "cobgs"


def _trajectory_record(scene: str, method: str, obj: str, stages=("mask", "texture", "mask", "check")) -> dict:
    return {"scene": scene, "method": method, "object": obj, "start": {"iou": 0.5, "biou": 0.3},
            "stages": [{"stage": i, "kind": k, "iou": 0.6 + 0.05 * i, "biou": 0.4 + 0.05 * i,
                        "cf_iou": 0.6, "cf_biou": 0.41} for i, k in enumerate(stages)]}


def test_trajectory_records_are_drawn_per_scene_of_the_run(recorded, tmp_path):
    """`--trajectories DIR`: one figure per scene of the run with records; other scenes'
    records are left out; the caption names the files it drew."""
    d = tmp_path / "traj"
    d.mkdir()
    (d / "s1__cobgs__ball.json").write_text(json.dumps(_trajectory_record("s1", "cobgs", "ball")))
    (d / "s1__ours__ball.json").write_text(json.dumps(_trajectory_record("s1", "ours", "ball")))  # not a run method
    (d / "elsewhere__cobgs__ball.json").write_text(json.dumps(_trajectory_record("elsewhere", "cobgs", "ball")))
    index = recorded.build(tmp_path / "r", trajectories=d)
    html = index.read_text(encoding="utf-8")
    svg = index.parent / "plots" / "trajectory-s1.svg"
    assert svg.is_file() and "plots/trajectory-s1.svg" in html
    assert "s1__cobgs__ball.json, s1__ours__ball.json" in html
    assert not list((index.parent / "plots").glob("trajectory-elsewhere*")) and "elsewhere__" not in html
    text = svg.read_text(encoding="utf-8")
    assert "cobgs / ball" in text and "ours / ball" in text
    # without the option: no such figure
    plain = recorded.build(tmp_path / "r2")
    assert not list((plain.parent / "plots").glob("trajectory-*"))


@pytest.mark.parametrize("mutate, match", [
    (lambda r: r.pop("scene"), r"field 'scene'"),
    (lambda r: r["stages"][1].update(kind="mystery"), r"stages\[1\]\.kind: expected one of mask, texture, check"),
    (lambda r: r["stages"][2].update(biou=float("nan")), r"stages\[2\]\.biou: expected a finite number"),
    (lambda r: r.update(stages=[]), r"field 'stages': expected a non-empty list"),
])
def test_a_bad_trajectory_record_stops_the_report_before_anything_is_written(recorded, tmp_path, mutate, match):
    d = tmp_path / "traj"
    d.mkdir()
    rec = _trajectory_record("s1", "cobgs", "ball")
    mutate(rec)
    (d / "bad.json").write_text(json.dumps(rec))
    with pytest.raises(ReportError, match=r"bad\.json: " + match):
        recorded.build(tmp_path / "r", trajectories=d)
    assert not (tmp_path / "r").exists()
    with pytest.raises(ReportError, match="not a folder"):
        recorded.build(tmp_path / "r", trajectories=tmp_path / "absent")
