"""NVOS and LERF-mask workflows end to end on scenes in the published layouts.

The scenes are a synthetic scene rewritten as an LLFF scene + NVOS labels and as a
LERF-mask scene (tests/stages/protocol_fixtures.py), so the ground truth is exact. Masks
come from files (SAM2 is not available offline); everything else is the real workflow:
ingestion of each layout, SfM, training, COB-GS and the three peers, the protocols'
evaluation (NEAREST resize to a 2x GT for NVOS, per-prompt means and skipped views for
LERF-mask) and the summary. Also: the NVOS / LERF-mask workflows fail fast without data.
"""

from __future__ import annotations

import io
import json

import pytest

from pipeline import RunOptions, WorkflowError, entries, load_workflow, run_workflow
from stages.registry import load_registry

from protocol_fixtures import to_lerf_mask, to_nvos  # tests/stages is on sys.path
from tiny_recipe import tiny_recipe  # tests/ is on sys.path

WORKFLOW = """
[workflow]
name = "protocols"
nested = {{ object = "scene" }}

{recipe}
[axes.scene.synthball]
kind = "nvos"
path = "{llff}"
labels = "{labels}"
dataset = {{ downscale = 2.0 }}

[axes.scene.lerf]
kind = "lerf_mask"
path = "{lerf}"

[axes.method.cobgs]
[axes.method.nosplit]
refine = {{ method = "nosplit" }}
[axes.method.sa3d]
refine = {{ method = "sa3d" }}
[axes.method.flashsplat]
refine = {{ method = "flashsplat" }}

[axes.object.synthball.ball]
[axes.object.lerf.ball]
[axes.object.lerf.can]
"""


def _area(path) -> int:
    import cv2

    return int((cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) > 128).sum())


def _over_segments_but_finds_the_object(metrics: dict) -> None:
    pv = metrics["details"]["per_view"].values()
    tp, fn = sum(v["tp"] for v in pv), sum(v["fn"] for v in pv)
    assert tp / (tp + fn) > 0.95 and metrics["row"]["iou"] > 0.25, metrics["row"]


@pytest.mark.slow
def test_nvos_and_lerf_mask_workflows(tmp_path):
    from cobgs.data.synth.scene import generate_scene
    from pipeline import entries

    scene = generate_scene(tmp_path / "synth", "demo", 0, num_views=16, progress=False)
    llff, labels = to_nvos(scene, tmp_path / "nvos", "synthball", "ball", target="0008", reference="0003")
    lerf, test_views = to_lerf_mask(scene, tmp_path / "lerf", {"ball": "ball", "can": "can"})
    path = tmp_path / "protocols.toml"
    path.write_text(WORKFLOW.format(llff=llff, labels=labels, lerf=lerf, recipe=tiny_recipe()))
    wf = load_workflow(path, load_registry())
    out = io.StringIO()
    summary = run_workflow(wf, RunOptions(cache_dir=tmp_path / "cache"), stream=out)
    assert summary.exit_code == 0, out.getvalue()

    recs = {(r.stage, r.item.id): r for r in entries(wf, tmp_path / "cache")}
    spec = json.loads((recs[("dataset", "synthball")].output("dataset") / "dataset.json").read_text())
    assert spec["protocol"] == "nvos" and spec["test_views"] == ["0008"] and "0008" not in \
        json.loads((recs[("train", "synthball")].output("scene") / "train.json").read_text())["train_views"]
    lspec = json.loads((recs[("dataset", "lerf")].output("dataset") / "dataset.json").read_text())
    assert lspec["protocol"] == "lerf_mask" and lspec["test_views"] == test_views
    assert lspec["objects"] == ["ball", "can"]

    rows = {}
    for method in ("cobgs", "nosplit", "sa3d", "flashsplat"):
        for item in (f"synthball/{method}/ball", f"lerf/{method}/ball", f"lerf/{method}/can"):
            m = json.loads((recs[("evaluate", item)].output("metrics") / "metrics.json").read_text())
            rows[item] = m
    # NVOS: one target view, compared at the GT's (2x) size after a NEAREST resize.
    for method in ("cobgs", "nosplit", "sa3d", "flashsplat"):
        m = rows[f"synthball/{method}/ball"]
        assert m["row"]["protocol"] == "nvos" and m["row"]["views"] == 1
        pv = m["details"]["per_view"]["0008"]
        assert pv["resized"] and (pv["height"], pv["width"]) == (240, 320)
        assert m["row"]["mask_render"] == "object_only"
        # the GT compared is the target's: its area is 4x the training-size exact mask's
        assert pv["tp"] + pv["fn"] == 4 * _area(scene / "masks" / "ball" / "0008.png")
    # Measured on this 500-iteration scene, 3 mask stages, SfM on one thread (repeatable;
    # 2026-11-27): COB-GS (the default, with the object check) 0.948, no split 0.955,
    # FlashSplat 0.954; SA3D-GS by its official rules 0.380 with every GT pixel found: its
    # 0.1 evaluation bar over-segments at this image size (docs/method.md §3). A mis-wired
    # protocol (wrong view, GT at the wrong size) loses the recall too.
    for method in ("cobgs", "nosplit", "flashsplat"):
        assert rows[f"synthball/{method}/ball"]["row"]["iou"] > 0.75, method
    _over_segments_but_finds_the_object(rows["synthball/sa3d/ball"])
    # LERF-mask: every GT file is scored (an empty GT: 0 against a non-empty prediction, NaN
    # against an empty one, both counted), views without a file are listed, and the GT of
    # test index i is the i-th sorted test view's (its area identifies it).
    for item, m in rows.items():
        if not item.startswith("lerf/"):
            continue
        assert m["row"]["protocol"] == "lerf_mask"
        assert set(m["details"]["per_view"]) | set(m["details"]["skipped"]) == set(test_views)
        finite = [pv for pv in m["details"]["per_view"].values()
                  if pv["iou"] is not None and pv["iou"] == pv["iou"]]  # NaN is null in JSON
        assert m["row"]["views"] == len(finite) > 0
        assert m["row"]["empty_gt_zero"] + m["row"]["empty_gt_nan"] == len(m["details"]["empty_gt"])
        obj = item.split("/")[-1]
        for view, pv in m["details"]["per_view"].items():
            assert pv["tp"] + pv["fn"] == _area(scene / "masks" / obj / f"{view[len('frame_'):]}.png"), view
    # Measured (2026-11-27): ball 0.946 / can 0.914 (COB-GS, the default), 0.946 / 0.880 (no
    # split), 0.947 / 0.879 (FlashSplat), SA3D-GS official 0.409 / 0.327 with recall 1.0 (the
    # 0.1 bar again); no test view of this fixture has an empty GT.
    for method in ("cobgs", "nosplit", "flashsplat"):
        for obj in ("ball", "can"):
            assert rows[f"lerf/{method}/{obj}"]["row"]["iou"] > 0.75, (method, obj)
    for obj in ("ball", "can"):
        _over_segments_but_finds_the_object(rows[f"lerf/sa3d/{obj}"])

    summ = json.loads((recs[("summary", "")].output("summary") / "summary.json").read_text())
    per = {(r["scene"], r["method"]): r for r in summ["by_scene_method"]}
    lerf_cobgs = per[("lerf", "cobgs")]
    assert lerf_cobgs["objects"] == 2
    assert lerf_cobgs["iou"] == pytest.approx((rows["lerf/cobgs/ball"]["row"]["iou"]
                                               + rows["lerf/cobgs/can"]["row"]["iou"]) / 2)
    assert summ["protocols"] == ["lerf_mask", "nvos"]


@pytest.mark.parametrize("name, env, message", [
    ("nvos.toml", {}, "NVOS_LLFF_DIR is not set"),
    ("nvos.toml", {"NVOS_LLFF_DIR": "/nonexistent", "NVOS_LABELS_DIR": "/nonexistent"},
     "data folder /nonexistent/fern (kind 'nvos') does not exist"),
    ("lerf_mask.toml", {}, "LERF_MASK_DIR is not set"),
    ("lerf_mask.toml", {"LERF_MASK_DIR": "/nonexistent"},
     "data folder /nonexistent/figurines (kind 'lerf_mask') does not exist"),
])
def test_benchmark_workflows_fail_fast_without_data(name, env, message):
    import re
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "workflows" / name
    with pytest.raises(WorkflowError, match=re.escape(message)):
        load_workflow(path, load_registry(), environ=env)


def test_every_missing_variable_is_named_at_once():
    """A user missing two variables learns both from one run, with the keys needing them."""
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "workflows" / "nvos.toml"
    with pytest.raises(WorkflowError) as info:
        load_workflow(path, load_registry(), environ={})
    text = str(info.value)
    assert "NVOS_LLFF_DIR is not set (axes.scene.fern.path" in text
    assert "NVOS_LABELS_DIR is not set (axes.scene.fern.labels" in text
    assert "export NVOS_LABELS_DIR=... NVOS_LLFF_DIR=..." in text


@pytest.mark.parametrize("name, scenes", [
    ("nvos.toml", ("fern", "flower", "fortress", "horns", "leaves", "orchids", "trex")),
    ("lerf_mask.toml", ("figurines", "ramen", "teatime")),
])
def test_benchmark_workflows_need_models_only_for_model_sources(tmp_path, name, scenes):
    """Without COBGS_MODELS_DIR the shipped workflows load; their model-backed mask source
    is refused when planned, naming the setting, and masks from files need no models."""
    from pathlib import Path

    from pipeline import Plan

    for s in scenes:
        (tmp_path / "data" / s).mkdir(parents=True)
    (tmp_path / "labels" / "masks").mkdir(parents=True)
    env = {"NVOS_LLFF_DIR": str(tmp_path / "data"), "NVOS_LABELS_DIR": str(tmp_path / "labels"),
           "LERF_MASK_DIR": str(tmp_path / "data")}
    path = Path(__file__).resolve().parents[2] / "workflows" / name
    with pytest.raises(WorkflowError, match="needs masks.models_dir, which is not set"):
        Plan(load_workflow(path, load_registry(), environ=env))
    (tmp_path / "released").mkdir()
    plan = Plan(load_workflow(path, load_registry(), ["masks.source=files",
                                                      f"masks.files_root={tmp_path / 'released'}"],
                              environ=env))
    assert plan.tasks


def test_onnx_masks_need_a_model_folder(tmp_path):
    """The masks stage's model-backed sources are refused when the workflow is planned."""
    from pipeline import Plan

    path = tmp_path / "w.toml"
    path.write_text('[workflow]\nnested = { object = "scene" }\n[params.masks]\nsource = "onnx"\n'
                    '[axes.scene.s]\nkind = "synthetic"\n[axes.method.cobgs]\n[axes.object.s.ball]\n')
    wf = load_workflow(path, load_registry())
    with pytest.raises(WorkflowError, match="masks.models_dir, which is not set"):
        Plan(wf)
    path.write_text(path.read_text().replace('source = "onnx"', f'source = "nvos"\nmodels_dir = "{tmp_path}/none"'))
    with pytest.raises(WorkflowError, match="does not exist"):
        Plan(load_workflow(path, load_registry()))


@pytest.mark.parametrize("layout", ["nerf_llff_data", "nex"])
def test_nvos_on_the_published_llff_copies_with_released_masks(tmp_path, layout):
    """Both published copies of the NVOS scenes load (nerf_llff_data: SIMPLE_RADIAL sparse/0,
    images_2/image000.png ...; NeX: 14-column poses_bounds + hwf_cxcy.npy), the target view
    is held out, and the released masks (<view>.JPG at full size) train the object: dataset
    -> ... -> evaluate, with the route and the reader's decisions in the artifacts."""
    from cobgs.data.synth.scene import generate_scene

    scene = generate_scene(tmp_path / "synth", "demo", seed=0, num_views=12, workers=1)
    llff, labels = to_nvos(scene, tmp_path / "nvos", "synthball", "ball", target="0008",
                           reference="0003", layout=layout)
    text = WORKFLOW.format(llff=llff, labels=labels, lerf=llff, recipe=tiny_recipe())
    text = text[:text.index("[axes.scene.lerf]")] + text[text.index("[axes.method.cobgs]"):]
    text = text.replace("[axes.object.lerf.ball]\n[axes.object.lerf.can]\n", "")
    text = text.replace("[axes.object.synthball.ball]",
                        f'[axes.object.synthball.ball]\nmask_dir = "{llff / "released_masks"}"')
    text = text.replace("[axes.method.nosplit]\nrefine = {{ method = \"nosplit\" }}", "")
    text += '\n[params.masks]\nsource = "files"\n'
    path = tmp_path / "nvos.toml"
    path.write_text(text)
    wf = load_workflow(path, load_registry(), [])
    out = io.StringIO()
    summary = run_workflow(wf, RunOptions(cache_dir=tmp_path / "cache", package_version="test",
                                          items="synthball/cobgs/ball"), stream=out)
    assert summary.exit_code == 0, out.getvalue()
    recs = {(r.stage, r.item.id): r for r in entries(wf, tmp_path / "cache")}
    spec = json.loads((recs[("dataset", "synthball")].output("dataset") / "dataset.json").read_text())
    assert spec["protocol"] == "nvos" and spec["test_views"] == ["0008"]
    assert "0008" in spec["views"] and "0003" in spec["views"]
    assert any("sorted order" in n for n in spec["notes"])
    if layout == "nerf_llff_data":
        assert any("SIMPLE_RADIAL" in n and "dropped" in n for n in spec["notes"])
    else:
        assert any("NeX" in n for n in spec["notes"])
    masks = json.loads((recs[("masks", "synthball/ball")].output("masks") / "masks.json").read_text())
    assert masks["route"] == "released masks (files)" and "0008" not in masks["files"]["files"]
    m = json.loads((recs[("evaluate", "synthball/cobgs/ball")].output("metrics") / "metrics.json").read_text())
    assert m["row"]["protocol"] == "nvos" and m["row"]["mask_route"] == "released masks (files)"
    assert m["row"]["iou"] > 0.7  # a mis-read camera or mask would score far lower
