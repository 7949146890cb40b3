"""NVOS inputs as a new user has them (issue 36 §3): the labels folder as the download
unpacks it, COB-GS's own output layout as released masks, NeX's ``*_undistort`` scene
names, downscales other than the pre-shrunk folders, and the message without models."""

from __future__ import annotations

import io
import json
import shutil
from pathlib import Path

import cv2
import pytest

from pipeline import Plan, RunOptions, WorkflowError, entries, load_workflow, run_workflow
from stages.registry import load_registry

from protocol_fixtures import run_stages, to_nvos  # tests/stages is on sys.path

WORKFLOW = """
[workflow]
name = "nvos_inputs"
nested = {{ object = "scene" }}
[params.sfm]
mode = "never"
[params.dataset]
downscale = {downscale}
[params.masks]
source = "files"
{files_root}
[axes.scene.synthball]
kind = "nvos"
path = "{llff}"
labels = "{labels}"
[axes.method.cobgs]
[axes.object.synthball.synthball]
mask = "ball"
"""


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    from cobgs.data.synth.scene import generate_scene

    return generate_scene(tmp_path_factory.mktemp("synth") / "s", "demo", seed=0, num_views=8, workers=1,
                          progress=False)


def _nvos(synth, out: Path, layout="nex", factor=2):
    return to_nvos(synth, out, "synthball", "ball", target="0005", reference="0002", layout=layout, factor=factor)


def _run(tmp_path, text, stages=("dataset", "sfm", "masks")):
    return run_stages(tmp_path, text, stages)


def test_labels_folder_as_the_download_unpacks_it(synth, tmp_path):
    """NVOS_LABELS_DIR at labels/ (holding llff/) reads labels/llff; a folder that is
    neither says where masks/ was looked for."""
    from cobgs.data.nvos import read_nvos_task
    from cobgs.errors import DataError

    llff, labels = _nvos(synth, tmp_path / "nvos")
    dl = tmp_path / "download" / "labels"
    dl.mkdir(parents=True)
    shutil.move(str(labels), str(dl / "llff"))
    task = read_nvos_task(dl, "synthball")
    assert task.target == "0005" and task.gt_mask.parent.parent.parent == dl / "llff"
    with pytest.raises(DataError, match=r"no masks/ in it nor in llff/.*labels/llff"):
        read_nvos_task(tmp_path / "download", "synthball")
    # the workflow takes labels/ as it is
    recs = _run(tmp_path, WORKFLOW.format(downscale=2.0, files_root="", llff=llff, labels=dl), ("dataset",))
    spec = json.loads((recs[("dataset", "synthball")].output("dataset") / "dataset.json").read_text())
    assert spec["nvos"]["target"] == "0005" and spec["test_views"] == ["0005"]
    # and a wrong folder is refused when the workflow is planned, naming it
    bad = WORKFLOW.format(downscale=2.0, files_root="", llff=llff, labels=tmp_path / "download")
    (tmp_path / "bad.toml").write_text(bad)
    with pytest.raises(WorkflowError, match="not an NVOS labels folder"):
        Plan(load_workflow(tmp_path / "bad.toml", load_registry()))


def test_nex_scene_named_undistort(synth, tmp_path):
    """fvdb / NeX copies live in scenes/<scene>_undistort: path = .../<scene> finds it."""
    llff, labels = _nvos(synth, tmp_path / "nvos")
    renamed = llff.parent / "synthball_undistort"
    llff.rename(renamed)
    recs = _run(tmp_path, WORKFLOW.format(downscale=2.0, files_root="", llff=llff.parent / "synthball",
                                          labels=labels), ("dataset",))
    spec = json.loads((recs[("dataset", "synthball")].output("dataset") / "dataset.json").read_text())
    assert spec["source"] == str(renamed.resolve())


def test_cobgs_output_layout_as_files_root(synth, tmp_path):
    """COB-GS writes output/<scene>/masks/<task>/<view>.JPG: masks.files_root = output/
    reads it as it is (one --set for every task, no per-task mask_dir)."""
    llff, labels = _nvos(synth, tmp_path / "nvos")
    out = tmp_path / "output" / "synthball" / "masks" / "synthball"
    out.mkdir(parents=True)
    for f in (llff / "released_masks").iterdir():
        shutil.copy(f, out / f.name)
    (tmp_path / "output" / "other_scene" / "masks" / "other_task").mkdir(parents=True)
    recs = _run(tmp_path, WORKFLOW.format(downscale=2.0, files_root=f'files_root = "{tmp_path / "output"}"',
                                          llff=llff, labels=labels))
    info = json.loads((recs[("masks", "synthball/synthball")].output("masks") / "masks.json").read_text())
    assert info["route"] == "released masks (files)" and info["files"]["dir"] == str(out)
    assert "0005" not in info["files"]["files"] and len(info["files"]["files"]) == 7


def test_other_downscales_keep_the_images_in_the_gt_frame(synth, tmp_path):
    """nerf_llff_data at a downscale without a pre-shrunk folder reads the full-size images;
    their SIMPLE_RADIAL camera is read as a pinhole (as at images_4/ and as the reference
    methods do), never undistorted away from the GT's frame, and dataset.json says so."""
    llff, labels = _nvos(synth, tmp_path / "nvos", layout="nerf_llff_data", factor=4)
    cams = llff / "sparse" / "0" / "cameras.txt"
    parts = cams.read_text().split()
    parts[-1] = "0.08"  # a visible k1: undistortion would change the image size
    cams.write_text(" ".join(parts) + "\n")
    shutil.rmtree(llff / "masks")  # (the fixture's per-view masks are at the synthetic size)
    full = cv2.imread(str(next((llff / "images").iterdir())))
    recs = _run(tmp_path, WORKFLOW.format(downscale=2.0, files_root="", llff=llff, labels=labels), ("dataset",))
    spec = json.loads((recs[("dataset", "synthball")].output("dataset") / "dataset.json").read_text())
    assert spec["reader"]["distortion"] == "ignore"
    assert any("captured frame" in n and "downscale 2" in n for n in spec["notes"])
    from stages._common import load_scene

    scene = load_scene(recs[("dataset", "synthball")].output("dataset"), None)
    gt = cv2.imread(spec["nvos"]["gt_mask"], cv2.IMREAD_GRAYSCALE)
    v = scene.views[0]
    assert (v.height * 2, v.width * 2) == full.shape[:2] == gt.shape[:2]


def test_shipped_nvos_workflow_says_how_to_run_without_models(tmp_path):
    env = {"NVOS_LLFF_DIR": str(tmp_path), "NVOS_LABELS_DIR": str(tmp_path / "labels"), "COBGS_MODELS_DIR": ""}
    for s in ("fern", "flower", "fortress", "horns", "leaves", "orchids", "trex"):
        (tmp_path / s).mkdir()
    (tmp_path / "labels" / "masks").mkdir(parents=True)
    path = Path(__file__).resolve().parents[2] / "workflows" / "nvos.toml"
    with pytest.raises(WorkflowError, match=r"--set masks\.source=files"):
        Plan(load_workflow(path, load_registry(), environ=env))


def test_two_tasks_on_one_scene_train_once(synth, tmp_path):
    """The two horns tasks share a scene: `task = [...]` trains it once, each task an object
    with its own GT; the means are over tasks (each task one unit), not over scenes."""
    from tiny_recipe import tiny_recipe  # tests/ is on sys.path

    from protocol_fixtures import write_nvos_labels

    llff, labels = to_nvos(synth, tmp_path / "nvos", "sh_center", "ball", target="0005", reference="0002")
    write_nvos_labels(synth, labels, "sh_left", "can", target="0005", reference="0002")
    text = f"""
[workflow]
name = "two_tasks"
nested = {{ object = "scene" }}
{tiny_recipe(iterations=150, densify_until_its=100, sfm="never", mask_stages=1)}
[params.dataset]
downscale = 2.0
[params.masks]
source = "files"
[axes.scene.sh]
kind = "nvos"
path = "{llff}"
labels = "{labels}"
task = ["sh_center", "sh_left"]
[axes.method.cobgs]
[axes.object.sh.sh_center]
mask = "ball"
[axes.object.sh.sh_left]
mask = "can"
"""
    path = tmp_path / "w.toml"
    path.write_text(text)
    wf = load_workflow(path, load_registry())
    plan = Plan(wf)
    assert [t.item.id for t in plan.tasks if t.stage.name == "train"] == ["sh"]
    out = io.StringIO()
    summary = run_workflow(wf, RunOptions(cache_dir=tmp_path / "cache"), stream=out)
    assert summary.exit_code == 0, out.getvalue()
    recs = {(r.stage, r.item.id): r for r in entries(wf, tmp_path / "cache")}
    spec = json.loads((recs[("dataset", "sh")].output("dataset") / "dataset.json").read_text())
    assert spec["objects"] == ["sh_center", "sh_left"] and spec["test_views"] == ["0005"]
    rows = {}
    for t in ("sh_center", "sh_left"):
        m = json.loads((recs[("evaluate", f"sh/cobgs/{t}")].output("metrics") / "metrics.json").read_text())
        rows[t] = m["row"]
        assert m["row"]["task"] == t
        pv = m["details"]["per_view"]["0005"]
        gt = cv2.imread(str(labels / "masks" / t / "0005_mask.png"), cv2.IMREAD_GRAYSCALE) > 128
        assert pv["tp"] + pv["fn"] == int(gt.sum())  # each task scored on its own GT
    s = json.loads((recs[("summary", "")].output("summary") / "summary.json").read_text())
    by = {r["method"]: r for r in s["by_method"]}
    assert by["cobgs"]["scenes"] == 2  # two units: the two tasks
    assert by["cobgs"]["iou"] == pytest.approx((rows["sh_center"]["iou"] + rows["sh_left"]["iou"]) / 2)
