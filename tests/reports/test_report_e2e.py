"""The report of a real run: the built-in stages on a tiny synthetic scene (minutes on a
loaded CPU, hence ``slow``), reported with ``cobgs report`` and opened in Chromium.

Checks that only real artifacts can satisfy: the report's numbers are the evaluate
stage's, the FP / FN pixel counts drawn under each overlay are the ones the protocol
counted on that view, the ambiguity curves cross the refine stage's recorded counts at
its δ, and the page loads cleanly.
"""

from __future__ import annotations

import io
import json
import re
from pathlib import Path

import numpy as np
import pytest
from tiny_recipe import tiny_recipe  # tests/ is on sys.path

pytestmark = pytest.mark.slow

WORKFLOW = """
[workflow]
name = "report_e2e"
nested = { object = "scene" }

[params.dataset]
preset = "demo"
num_views = 16
workers = 1

{recipe}
[axes.scene.tiny]
kind = "synthetic"

[axes.method.cobgs]
[axes.method.nosplit]
refine = { method = "nosplit" }
[axes.method.flashsplat]
refine = { method = "flashsplat" }

[axes.object.tiny.ball]
""".replace("{recipe}", tiny_recipe(iterations=300, densify_until_its=250, sfm="never", stage_length_views=1.0))


@pytest.fixture(scope="module")
def real(tmp_path_factory):
    from pipeline import RunOptions, load_workflow, run_workflow
    from stages.registry import load_registry

    root = tmp_path_factory.mktemp("report_e2e")
    path = root / "tiny.toml"
    path.write_text(WORKFLOW)
    cache = root / "cache"
    out = io.StringIO()
    summary = run_workflow(load_workflow(path, load_registry(), []), RunOptions(cache_dir=cache, package_version="test"),
                           stream=out)
    assert summary.exit_code == 0, out.getvalue()
    from stages.commands.cli import main

    assert main(["report", str(path), "--cache-dir", str(cache), "--out", str(root / "report")]) == 0
    return path, cache, root / "report" / "index.html"


def _evaluate_rows(cache: Path) -> dict:
    out = {}
    for f in (cache / "entries" / "evaluate").glob("*/out/metrics.json"):
        m = json.loads(f.read_text())
        out[m["row"]["method"]] = m
    return out


def test_numbers_are_the_evaluate_stage_numbers(real):
    _, cache, index = real
    rows = _evaluate_rows(cache)
    record = json.loads((index.parent / "report.json").read_text())
    for r in record["by_method"]:
        m = rows[r["method"]]["row"]
        for k in ("iou", "acc", "biou", "psnr", "psnr_delta"):
            assert r[k] == pytest.approx(m[k], abs=1e-12), (r["method"], k)


def test_overlay_counts_are_the_protocol_counts(real):
    _, cache, index = real
    rows = _evaluate_rows(cache)
    html = index.read_text(encoding="utf-8")
    view = re.search(r'class="view">held-out view ([^<]+)<', html).group(1)
    for method, m in rows.items():
        s = m["details"]["per_view"][view]
        cell = html[html.index(f'<span class="mname">{method}</span>'):]
        got = re.search(r"FP ([\d\u2009]+) px · FN ([\d\u2009]+) px", cell)
        assert (int(got.group(1).replace("\u2009", "")), int(got.group(2).replace("\u2009", ""))) == \
            (s["fp"], s["fn"]), method


def test_ambiguity_curve_matches_the_recorded_counts(real):
    _, cache, _ = real
    for d in (cache / "entries" / "refine").glob("*/out"):
        info = json.loads((d / "refine.json").read_text())
        if info["method"] != "cobgs":
            continue
        with np.load(d / "stage_scores.npz") as z:
            scores = [z[f"stage_{i}"] for i in range(len(z.files))]
        masks = [s for s in info["stages"] if s["kind"] == "mask"]
        assert len(masks) == len(scores) == 3
        for st, sc in zip(masks, scores):
            assert int((sc < info["delta"]).sum()) == st["ambiguous"]


def test_page_loads_cleanly(real, tmp_path):
    from report_browser import CHROMIUM, Browser

    if not Path(CHROMIUM).exists():
        pytest.skip(f"{CHROMIUM} missing")
    _, _, index = real
    with Browser() as b:
        b.goto(index.resolve().as_uri())
        assert b.errors() == []
        assert b.eval("Array.from(document.images).filter(i => !(i.complete && i.naturalWidth > 0)).length") == 0
        assert all(u.startswith(("file://", "data:")) for u in b.requested_urls())
        b.screenshot(tmp_path / "e2e.png")
