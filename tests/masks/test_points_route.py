"""``masks.source = "points"`` through the real workflow: the masks stage on a scene in a
published layout, the stand-in SAM2 exports (tests/masks/fakes.py) and click files in
both layouts (SAGA-v2's NVOS input points, the per-object one)."""

from __future__ import annotations

import io
import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline import RunOptions, WorkflowError, load_workflow, run_workflow
from stages.registry import load_registry

from . import scenes

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "stages"))
from protocol_fixtures import published_names, run_stages, write_llff, write_nvos_labels  # noqa: E402

N = 8


def _square_scene(root: Path) -> tuple[Path, list[np.ndarray]]:
    """A drifting red square in the layout of a synthetic scene (transforms.json with
    per-frame intrinsics, images/, masks/square/), 64x48, cameras stepping sideways."""
    paths, gts = scenes.write_sequence(root / "images", [scenes.Frame("red", x=6 + 5 * i, y=8 + 2 * i)
                                                         for i in range(N)])
    frames = []
    for i, p in enumerate(paths):
        frames.append({"file_path": f"images/{p.name}", "w": scenes.W, "h": scenes.H, "fl_x": 60.0,
                       "fl_y": 60.0, "cx": scenes.W / 2, "cy": scenes.H / 2,
                       "transform_matrix": [[1, 0, 0, 0.05 * i], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]})
        (root / "masks" / "square").mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(root / "masks" / "square" / p.name), gts[i].astype(np.uint8) * 255)
    (root / "transforms.json").write_text(json.dumps({"frames": frames}))
    return root, gts


def _centre(gt: np.ndarray) -> list[float]:
    y, x = np.argwhere(gt).mean(0)
    return [float(x), float(y)]


def _run(tmp_path, toml: str):
    return run_stages(tmp_path, toml, name="clicks.toml")


OWN = """
[workflow]
name = "clicks"
nested = {{ object = "scene" }}
[params.sfm]
mode = "never"
[params.dataset]
test_every = 4
[params.masks]
source = "points"
models_dir = "{models}"
points_file = "{clicks}"
[axes.scene.sq]
kind = "transforms"
path = "{scene}"
[axes.method.cobgs]
[axes.object.sq.square]
"""


def test_points_route_per_object_layout(models_dir, tmp_path):
    scene, gts = _square_scene(tmp_path / "scene")
    # Clicks given at 2x the image size (image_size says so): the route scales them.
    clicks = {"objects": {"square": {"image_size": [2 * scenes.W, 2 * scenes.H], "frames": {
        "0002": {"positive": [[2 * c for c in _centre(gts[2])]], "negative": [[2.0, 2.0]]},
        "0006": {"positive": [[2 * c for c in _centre(gts[6])]]}}}}}
    cf = tmp_path / "clicks.json"
    cf.write_text(json.dumps(clicks))
    recs = _run(tmp_path, OWN.format(models=models_dir, clicks=cf, scene=scene))
    out = recs[("masks", "sq/square")].output("masks")
    info = json.loads((out / "masks.json").read_text())
    assert info["source"] == "points" and info["route"] == "clicks -> SAM2"
    c = info["clicks"]
    assert c["file"] == str(cf) and c["layout"] == "objects" and c["entry"] == "square"
    assert [f["frame"] for f in c["frames"]] == ["0002", "0006"]
    assert c["frames"][0]["from_size"] == [2 * scenes.W, 2 * scenes.H]
    assert c["frames"][0]["image_size"] == [scenes.W, scenes.H]
    assert c["frames"][0]["positive"] == 1 and c["frames"][0]["negative"] == 1
    np.testing.assert_allclose(c["frames"][0]["points_px"][0], _centre(gts[2]), atol=0.01)
    assert [p["stem"] for p in info["generator"]["prompts"]] == ["0002", "0006"]
    # masks named after the training views (0000 and 0004 are held out), each on its square
    assert sorted(p.stem for p in out.glob("*.png")) == ["0001", "0002", "0003", "0005", "0006", "0007"]
    for p in out.glob("*.png"):
        m = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) > 127
        assert scenes.iou(m, gts[int(p.stem)]) > 0.8, p.name


def test_points_route_saga_v2_file_on_an_nvos_scene_in_the_published_layout(models_dir, tmp_path):
    """NeX layout (images_2/image000.png ..., views IMG_* from images/), NVOS labels, and a
    click file with the SAGA-v2 structure: quarter... here half-resolution values with
    ``_scale`` 2, keyed by the scene's base name (``sqr`` for task ``sqr_center``)."""
    scene, gts = _square_scene(tmp_path / "scene")
    stems = [f"{i:04d}" for i in range(N)]
    pub = published_names("IMG_4027", "IMG_4031", N)
    names = dict(zip(stems, pub))
    target, reference = stems[pub.index("IMG_4027")], stems[pub.index("IMG_4031")]
    llff = write_llff(scene, tmp_path / "nvos" / "llff", "nex", {}, names=names, factor=2)
    labels = write_nvos_labels(scene, tmp_path / "nvos" / "labels", "sqr_center", "square", target, reference,
                               names=names, factor=2)
    assert (llff / "images_2" / "image000.png").is_file()
    ref_gt = gts[stems.index(reference)]
    # full resolution = 2x the images; values x _scale are full-resolution pixels
    saga = {"_comment": "SAGA v2 style", "_scale": 2, "sqr": [_centre(ref_gt)], "other": [[1, 1]]}
    cf = tmp_path / "saga_v2_input_points.json"
    cf.write_text(json.dumps(saga))
    toml = f"""
[workflow]
name = "nvos_clicks"
nested = {{ object = "scene" }}
[params.sfm]
mode = "never"
[params.masks]
source = "points"
models_dir = "{models_dir}"
points_file = "{cf}"
[axes.scene.sqr]
kind = "nvos"
path = "{llff}"
labels = "{labels}"
task = "sqr_center"
dataset = {{ downscale = 2.0 }}
[axes.method.cobgs]
[axes.object.sqr.sqr_center]
"""
    recs = _run(tmp_path, toml)
    out = recs[("masks", "sqr/sqr_center")].output("masks")
    info = json.loads((out / "masks.json").read_text())
    c = info["clicks"]
    assert c["layout"] == "saga_v2" and c["entry"] == "sqr" and c["scale"] == 2
    assert [f["frame"] for f in c["frames"]] == ["IMG_4031"]  # the reference view
    assert c["frames"][0]["image"] == f"image{pub.index('IMG_4031'):03d}.png"
    assert c["frames"][0]["from_size"] == [2 * scenes.W, 2 * scenes.H]
    np.testing.assert_allclose(c["frames"][0]["points_px"][0], _centre(ref_gt), atol=0.01)
    # masks named after the views (IMG_*), not the images_2 files; the target held out
    got = sorted(p.stem for p in out.glob("*.png"))
    assert got == sorted(n for n in pub if n != "IMG_4027")
    for stem, name in names.items():
        if name == "IMG_4027":
            continue
        m = cv2.imread(str(out / f"{name}.png"), cv2.IMREAD_GRAYSCALE) > 127
        assert scenes.iou(m, gts[stems.index(stem)]) > 0.8, name


@pytest.mark.parametrize("edit, match", [
    ({"objects": {"square": {"frames": {"0002": {"positive": [[1, "x"]]}}}}},
     r"clicks\.json: object 'square', frame '0002': positive point 0"),
    ({"objects": {"square": {"frames": {"0002": {"negative": [[1, 1]]}}}}},
     r"object 'square', frame '0002': needs at least one positive click"),
])
def test_bad_click_file_refused_when_the_workflow_loads(models_dir, tmp_path, edit, match):
    """Refused when the workflow is planned (`cobgs run` / `status` / `--dry-run`), before
    any task runs."""
    from pipeline import Plan

    cf = tmp_path / "clicks.json"
    cf.write_text(json.dumps(edit))
    path = tmp_path / "clicks.toml"
    path.write_text(OWN.format(models=models_dir, clicks=cf, scene=tmp_path))
    with pytest.raises(WorkflowError, match=match):
        Plan(load_workflow(path, load_registry()))


@pytest.mark.parametrize("frames, match", [
    ({"0004": {"positive": [[10, 10]]}}, r"object 'square', frame '0004': a held-out view"),
    ({"IMG_9": {"positive": [[10, 10]]}}, r"frame 'IMG_9': no training view of that name"),
    ({"0002": {"positive": [[100, 10]]}}, r"frame '0002': click \[100.0, 10.0\] lies outside the image \(64x48"),
])
def test_click_file_checked_against_the_scene_before_sam2_runs(models_dir, tmp_path, frames, match):
    scene, _ = _square_scene(tmp_path / "scene")
    cf = tmp_path / "clicks.json"
    cf.write_text(json.dumps({"objects": {"square": {"frames": frames}}}))
    path = tmp_path / "clicks.toml"
    path.write_text(OWN.format(models=models_dir, clicks=cf, scene=scene))
    wf = load_workflow(path, load_registry())
    out = io.StringIO()
    summary = run_workflow(wf, RunOptions(cache_dir=tmp_path / "cache", only=("dataset", "sfm", "masks")), stream=out)
    assert summary.exit_code != 0
    assert str(cf) in out.getvalue()
    import re

    assert re.search(match, out.getvalue()), out.getvalue()[-2000:]


def test_click_mistakes_stop_the_run_after_the_dataset_before_sfm(models_dir, tmp_path):
    """Issue 44 M3 / H3: a wrong object key is refused when the run is planned (no task runs);
    a misspelt, extension-carrying or held-out frame, or clicks of another aspect, once the
    dataset task has listed the views: before SfM and training (hours on a real scene)."""
    scene, _ = _square_scene(tmp_path / "scene")
    cf = tmp_path / "clicks.json"
    path = tmp_path / "clicks.toml"
    path.write_text(OWN.format(models=models_dir, clicks=cf, scene=scene))

    def run(data, cache):
        cf.write_text(json.dumps(data))
        out = io.StringIO()
        summary = run_workflow(load_workflow(path, load_registry(), ["train.iterations=1"]),
                               RunOptions(cache_dir=tmp_path / cache, only=("dataset", "sfm", "train", "masks")),
                               stream=out)
        return summary, out.getvalue()

    cf.write_text(json.dumps({"objects": {"squar": {"frames": {"0001": {"positive": [[10, 10]]}}}}}))
    with pytest.raises(WorkflowError, match=r"masks\[sq/square\]\): click file .*clicks.json: no object for "
                                            r"'square' .*\['squar'\]"):
        run({"objects": {"squar": {"frames": {"0001": {"positive": [[10, 10]]}}}}}, "c0")
    assert not (tmp_path / "c0" / "entries").exists()  # nothing ran
    for i, (frames, size, match) in enumerate((
            ({"0010": {"positive": [[10, 10]]}}, None, r"frame '0010': no training view of that name; did you mean"),
            ({"0001.png": {"positive": [[10, 10]]}}, None, r"frame '0001.png': frames are named without the file "
                                                           r"extension: '0001'"),
            ({"0004": {"positive": [[10, 10]]}}, None, r"frame '0004': a held-out view"),
            ({"0001": {"positive": [[10, 10]]}}, [48, 64], r"frame '0001': the clicks are in a 48x64 frame, but the "
                                                           r"view's image .*0001.png is 64x48"))):
        obj = {"frames": frames, **({"image_size": size} if size else {})}
        summary, log = run({"objects": {"square": obj}}, f"c{i + 1}")
        states = {summary.plan.tasks[j].stage.name: o.state for j, o in summary.outcomes.items()}
        assert summary.exit_code == 1 and states == {"dataset": "done"}, (states, log)  # no SfM, no training
        import re

        assert re.search(match, summary.stopped) and "run stopped" in log, log
    # with the dataset already cached, the same mistake is refused when the run is planned
    with pytest.raises(WorkflowError, match=r"frame '0001': the clicks are in a 48x64 frame"):
        run({"objects": {"square": {"image_size": [48, 64], "frames": {"0001": {"positive": [[10, 10]]}}}}}, "c4")
    # the same clicks at a size of the same aspect are scaled and used
    summary, log = run({"objects": {"square": {"image_size": [128, 96], "frames": {"0001": {"positive": [[36, 30]]}}}}},
                       "c9")
    states = {summary.plan.tasks[j].stage.name: o.state for j, o in summary.outcomes.items()}
    assert states.get("masks") == "done", log


def test_clicks_that_find_nothing_say_where_they_landed_and_keep_masks_json(models_dir, tmp_path):
    """Issue 44 (click-route messages): when every mask comes out empty the failure names
    the frames and the pixels the clicks landed on, and masks.json is kept beside the log."""
    scene, _ = _square_scene(tmp_path / "scene")
    cf = tmp_path / "clicks.json"
    cf.write_text(json.dumps({"objects": {"square": {"frames": {"0002": {"positive": [[62, 46]]}}}}}))
    path = tmp_path / "clicks.toml"
    path.write_text(OWN.format(models=models_dir, clicks=cf, scene=scene))
    out = io.StringIO()
    summary = run_workflow(load_workflow(path, load_registry()),
                           RunOptions(cache_dir=tmp_path / "cache", only=("dataset", "sfm", "masks")), stream=out)
    assert summary.exit_code == 1
    failed = next(o for o in summary.outcomes.values() if o.state == "failed")
    assert "no training view got a non-empty mask" in failed.note
    assert "the clicks landed at 0002 (0002.png, 64x48 px): 1 positive at [[62.0, 46.0]]" in failed.note, failed.note
    kept = Path(failed.log_path).parent / "out" / "masks.json"
    info = json.loads(kept.read_text())
    assert info["clicks"]["frames"][0]["points_px"] == [[62.0, 46.0]] and info["empty"]
    assert sorted(p.name for p in kept.parent.iterdir()) == ["masks.json"]  # no mask PNG kept


def test_saga_clicks_on_a_scene_that_is_not_nvos_stop_before_sfm(models_dir, tmp_path):
    """Issue 56 M8: SAGA-layout clicks (NVOS reference-view clicks) on a non-NVOS scene were
    refused only when the masks task ran, after SfM and training. The dataset task says what
    kind the scene is; the run stops right after it."""
    scene, _ = _square_scene(tmp_path / "scene")
    cf = tmp_path / "saga.json"
    cf.write_text(json.dumps({"_scale": 1, "square": [[10, 10]]}))
    path = tmp_path / "clicks.toml"
    path.write_text(OWN.format(models=models_dir, clicks=cf, scene=scene))
    out = io.StringIO()
    summary = run_workflow(load_workflow(path, load_registry(), ["train.iterations=1"]),
                           RunOptions(cache_dir=tmp_path / "c", only=("dataset", "sfm", "train", "masks")), stream=out)
    states = {summary.plan.tasks[j].stage.name: o.state for j, o in summary.outcomes.items()}
    assert summary.exit_code == 1 and states == {"dataset": "done"}, (states, out.getvalue())
    assert "SAGA-v2 clicks belong on an NVOS task's reference view" in summary.stopped
    assert "is not an NVOS scene" in summary.stopped


def test_interior_clicks_sit_inside_and_spread():
    from cobgs.masks.clicks import interior_clicks

    m = np.zeros((40, 60), bool)
    m[10:30, 5:55] = True  # a 50x20 bar
    pts = interior_clicks(m, 3)
    assert pts.shape == (3, 2) and all(m[int(y), int(x)] for x, y in pts)
    assert 9 <= pts[0, 1] <= 20 and abs(pts[0, 0] - 29.5) <= 20  # on the bar's middle row band
    assert np.ptp(pts[:, 0]) > 20  # spread along the bar, not piled on the centre
    np.testing.assert_array_equal(pts, interior_clicks(m, 3))  # deterministic
    one = np.zeros((5, 5), bool)
    one[2, 3] = True
    assert interior_clicks(one, 4).tolist() == [[3.0, 2.0]]
    with pytest.raises(Exception, match="empty mask"):
        interior_clicks(np.zeros((4, 4), bool), 1)


def test_prompt_clicks_route_on_a_spin_scene(models_dir, tmp_path):
    """SPIn-NeRF's click route: clicks inside the prompt view's GT mask (the first annotated
    view), SAM2 on that view, propagated; a scene of another kind is refused in one line."""
    from protocol_fixtures import spin_published

    release, rgb = spin_published(tmp_path / "spin", {"fern": 20})
    toml = f"""
[workflow]
name = "spin_clicks"
nested = {{ object = "scene" }}
[params.sfm]
mode = "never"
[params.dataset]
downscale = 4.0
[params.masks]
source = "prompt_clicks"
models_dir = "{models_dir}"
prompt_clicks = 2
[axes.scene.fern]
kind = "spin"
path = "{rgb['fern']}"
labels = "{release}"
[axes.method.cobgs]
[axes.object.fern.object]
"""
    recs = run_stages(tmp_path, toml, name="spin_clicks.toml")
    out = recs[("masks", "fern/object")].output("masks")
    info = json.loads((out / "masks.json").read_text())
    assert info["source"] == "prompt_clicks" and info["route"] == "clicks in the prompt view's mask -> SAM2"
    frame = info["clicks"]["frames"][0]
    assert frame["frame"] == "IMG_4026" and frame["positive"] == 2 and frame["from"].endswith("image000.png")
    gt = cv2.imread(frame["from"], cv2.IMREAD_GRAYSCALE) > 127
    w, h = frame["image_size"]
    gt = cv2.resize(gt.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0
    assert all(gt[int(y), int(x)] for x, y in frame["points_px"])
    assert [p["stem"] for p in info["generator"]["prompts"]] == ["IMG_4026"]
    assert len(list(out.glob("*.png"))) >= 1
    # the route on a scene that is not SPIn-NeRF: one line naming the kind
    scene, _ = _square_scene(tmp_path / "sq")
    bad = OWN.format(models=models_dir, clicks="", scene=scene).replace('source = "points"', 'source = "prompt_clicks"')
    bad = bad.replace('points_file = ""\n', "")
    from pipeline import entries  # noqa: F401

    path = tmp_path / "bad.toml"
    path.write_text(bad)
    wf = load_workflow(path, load_registry())
    log = io.StringIO()
    summary = run_workflow(wf, RunOptions(cache_dir=tmp_path / "cache2", only=("dataset", "sfm", "masks")), stream=log)
    assert summary.exit_code != 0 and "is of kind 'transforms' (use 'points' with a click file)" in log.getvalue()
