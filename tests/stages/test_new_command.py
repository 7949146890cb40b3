"""`cobgs new FOLDER`: the layout it detects, the workflow it writes (which loads), and the
clear refusals (loose photos, no masks and no prompt, an existing file)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from stages.commands.cli import main


def _png(path, w=32, h=24):
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.full((h, w, 3), 128, np.uint8))


def _load(path, env=None):
    from pipeline import Plan, load_workflow
    from stages.registry import load_registry

    return Plan(load_workflow(path, load_registry(), environ=env))


@pytest.mark.parametrize("layout, kind", [
    ({"images/a.png": 1, "images/b.png": 1}, "images"),
    ({"images/a.png": 1, "sparse/0/cameras.txt": 0, "sparse/0/images.txt": 0, "sparse/0/points3D.txt": 0},
     "colmap"),
    ({"images/a.png": 1, "poses_bounds.npy": 0}, "llff"),
    ({"images/a.png": 1, "transforms.json": 0}, "transforms"),
])
def test_detects_the_layout_and_writes_a_workflow_that_loads(tmp_path, layout, kind, capsys):
    root = tmp_path / "my scene"
    for rel, is_image in layout.items():
        if is_image:
            _png(root / rel)
        else:
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            (root / rel).write_text("")
    _png(root / "masks" / "red mug" / "a.png")
    out = tmp_path / "w.toml"
    assert main(["new", str(root), "--out", str(out)]) == 0
    text = out.read_text()
    assert f'kind = "{kind}"' in text and 'source = "files"' in text and "# Written by `cobgs new" in text
    assert "# scene_type = " in text  # the forward / 360 choice is spelled out
    assert f"{kind!r}" in capsys.readouterr().out
    if kind == "images":
        plan = _load(out)
        assert {t.item.id for t in plan.tasks if t.stage.name == "masks"} == {"my scene/red mug"}


def test_prompts_select_the_text_route(tmp_path):
    root = tmp_path / "cap"
    _png(root / "images" / "a.png")
    out = tmp_path / "w.toml"
    assert main(["new", str(root), "--out", str(out), "--prompt", "a red mug", "--prompt", "spoon"]) == 0
    text = out.read_text()
    assert 'source = "onnx"' in text and 'models_dir = "${COBGS_MODELS_DIR}"' in text
    assert 'prompt = "a red mug"' in text and '[axes.object."cap"."spoon"]' in text
    (tmp_path / "models").mkdir()
    from pipeline import WorkflowError

    # issue 56 M8: a models folder without manifest.json is refused when the workflow loads
    with pytest.raises(WorkflowError, match="no manifest.json in the model folder"):
        _load(out, {"COBGS_MODELS_DIR": str(tmp_path / "models")})
    _manifest(tmp_path / "models", gdino=False)
    with pytest.raises(WorkflowError, match=r"has no Grounding DINO .* which masks.source 'onnx' needs"):
        _load(out, {"COBGS_MODELS_DIR": str(tmp_path / "models")})
    _manifest(tmp_path / "models")
    plan = _load(out, {"COBGS_MODELS_DIR": str(tmp_path / "models")})
    assert {t.item.id for t in plan.tasks if t.stage.name == "masks"} == {"cap/a red mug", "cap/spoon"}


def _manifest(root: Path, gdino: bool = True) -> None:
    """A model folder's manifest.json and (empty) files: what the load-time check reads."""
    from cobgs.masks.manifest import gdino_manifest_dict, sam2_manifest_dict, write_manifest

    entries = {"sam2": sam2_manifest_dict()}
    if gdino:
        entries["groundingdino"] = gdino_manifest_dict((800, 800))
    for entry in entries.values():
        for name in entry["files"].values():
            (root / name).parent.mkdir(parents=True, exist_ok=True)
            (root / name).write_bytes(b"")
    write_manifest(root, entries)


def test_refusals_say_what_to_do(tmp_path, capsys):
    loose = tmp_path / "loose"
    _png(loose / "IMG_1.png")
    assert main(["new", str(loose), "--out", str(tmp_path / "a.toml")]) == 2
    assert "move them into images/" in capsys.readouterr().err
    bare = tmp_path / "bare"
    _png(bare / "images" / "a.png")
    assert main(["new", str(bare), "--out", str(tmp_path / "b.toml")]) == 2
    assert "--prompt" in capsys.readouterr().err and not (tmp_path / "b.toml").exists()
    _png(bare / "masks" / "cup" / "a.png")
    (tmp_path / "c.toml").write_text("mine")
    assert main(["new", str(bare), "--out", str(tmp_path / "c.toml")]) == 2
    assert "--force" in capsys.readouterr().err and (tmp_path / "c.toml").read_text() == "mine"
    assert main(["new", str(bare), "--out", str(tmp_path / "c.toml"), "--force"]) == 0


# -- issue 38 M7: whatever `new` writes loads, and its objects find their mask folders -------
def test_renamed_mask_folders_map_back_and_collisions_stay_valid(tmp_path):
    import tomllib

    from stages.masks import ObjectAttrs  # noqa: F401  (the object schema the file must satisfy)

    root = tmp_path / "cap"
    _png(root / "images" / "a.png")
    for folder in (".hid", "a,b", "a=b", "plain"):
        _png(root / "masks" / folder / "a.png")
    out = tmp_path / "w.toml"
    assert main(["new", str(root), "--out", str(out)]) == 0
    data = tomllib.loads(out.read_text())
    objs = data["axes"]["object"]["cap"]
    assert objs["hid"]["mask"] == ".hid" and objs["a_b"]["mask"] == "a,b" and objs["a_b_2"]["mask"] == "a=b"
    assert "mask" not in objs["plain"]
    plan = _load(out)
    masks = {t.item["object"]: getattr(t.item.attrs["object"], "mask", "") for t in plan.tasks
             if t.stage.name == "masks"}
    assert masks == {"hid": ".hid", "a_b": "a,b", "a_b_2": "a=b", "plain": ""}


@pytest.mark.parametrize("bad", ["new\nline", "tab\there", 'quote"s', "back\\slash"])
def test_control_characters_in_names_and_prompts_write_valid_toml(tmp_path, bad):
    import tomllib

    root = tmp_path / f"cap {bad}" if "\n" not in bad else tmp_path / "cap\nx"
    _png(root / "images" / "a.png")
    out = tmp_path / "w.toml"
    assert main(["new", str(root), "--out", str(out), "--prompt", bad]) == 0
    data = tomllib.loads(out.read_text())
    scene = next(iter(data["axes"]["scene"].values()))
    assert scene["path"] == str(root)
    obj = next(iter(next(iter(data["axes"]["object"].values())).values()))
    assert obj["prompt"] == bad


def test_out_into_a_missing_folder_or_onto_a_folder_is_refused_cleanly(tmp_path, capsys):
    root = tmp_path / "cap"
    _png(root / "images" / "a.png")
    _png(root / "masks" / "m" / "a.png")
    assert main(["new", str(root), "--out", str(tmp_path / "nope" / "w.toml")]) == 2
    assert "does not exist" in capsys.readouterr().err
    (tmp_path / "dir.toml").mkdir()
    assert main(["new", str(root), "--out", str(tmp_path / "dir.toml"), "--force"]) == 2
    assert "is a folder" in capsys.readouterr().err
    assert not [p for p in tmp_path.iterdir() if ".tmp" in p.name or p.name.startswith(".cobgs-new")]


def test_new_and_the_readers_agree_on_the_layout(tmp_path):
    """Issue 39: one layout detector. A folder holding both transforms.json and
    transforms_train.json is the NeRF-synthetic layout for `cobgs new` and for the readers."""
    from cobgs.data.readers import detect_format
    from stages.commands.new import detect

    root = tmp_path / "both"
    _png(root / "images" / "a.png")
    (root / "transforms.json").write_text("{}")
    (root / "transforms_train.json").write_text("{}")
    _png(root / "masks" / "m" / "a.png")
    assert detect(root)["kind"] == detect_format(root) == "blender"


@pytest.mark.parametrize("images, every, block", [(12, 4, "2.5"), (20, 8, None), (8, 0, "2.8")])
def test_few_photos_get_stages_long_enough_for_the_labels(tmp_path, images, every, block):
    """With fewer than 11 training views, stages of 2V iterations are shorter than the 22 a
    split Gaussian's label needs to reach the foreground (docs/method.md §2, "Few views"):
    the workflow `cobgs new` writes sets the stage length that suffices, and says why."""
    from pipeline import load_workflow
    from stages.registry import load_registry

    root = tmp_path / "cap"
    for i in range(images):
        _png(root / "images" / f"{i:03d}.png")
    _png(root / "masks" / "mug" / "000.png")
    out = tmp_path / "w.toml"
    assert main(["new", str(root), "--out", str(out), "--test-every", str(every)]) == 0
    text = out.read_text()
    if block is None:
        assert "stage_length_views" not in text
        return
    views = images - (-(-images // every) if every else 0)
    assert f"# {views} training views" in text and f"stage_length_views = {block}\n" in text
    wf = load_workflow(out, load_registry())
    item = next(t for t in __import__("pipeline").Plan(wf).tasks if t.stage.name == "refine")
    assert item.params.value.cobgs.stage_length_views == float(block)
    assert float(block) * views >= 22 > (float(block) - 0.1) * views


def _jpeg(path, w=32, h=24, orientation=None):
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    im = Image.fromarray(np.full((h, w, 3), 128, np.uint8))
    exif = Image.Exif()
    if orientation is not None:
        exif[0x0112] = orientation
    im.save(path, exif=exif)


def test_test_every_that_cannot_work_is_refused_before_writing(tmp_path, capsys):
    """Issue 44 L1: --test-every -1 wrote a workflow `cobgs run` refuses; 1 held out every image."""
    root = tmp_path / "cap"
    for n in ("a", "b", "c"):
        _png(root / "images" / f"{n}.png")
    _png(root / "masks" / "cup" / "a.png")
    for bad in ("-1", "1", "x"):
        with pytest.raises(SystemExit):
            main(["new", str(root), "--out", str(tmp_path / "w.toml"), "--test-every", bad])
        assert "--test-every" in capsys.readouterr().err and not (tmp_path / "w.toml").exists()
    assert main(["new", str(root), "--out", str(tmp_path / "w.toml"), "--test-every", "0"]) == 0
    from cobgs.configs import DatasetConfig

    with pytest.raises(ValueError, match="test_every = 1 holds out every view"):
        DatasetConfig(test_every=1)


def test_unreadable_empty_mixed_and_rotated_photos_are_said(tmp_path, capsys):
    """Issue 44 L6 (unreadable and empty files were counted, mixed sizes unmentioned) and H3
    (EXIF orientation: refused with the fix, where every reader would otherwise disagree)."""
    root = tmp_path / "cap"
    _png(root / "images" / "a.png")
    _png(root / "images" / "b.png")
    _png(root / "images" / "c.png", 24, 32)
    (root / "images" / "empty.jpg").write_bytes(b"")
    (root / "images" / "junk.png").write_bytes(b"not a png at all")
    _png(root / "masks" / "cup" / "a.png")
    out = tmp_path / "w.toml"
    assert main(["new", str(root), "--out", str(out)]) == 0
    cap = capsys.readouterr()
    assert "3 images" in cap.out and "2 x 32x24, 1 x 24x32" in cap.out
    assert "empty.jpg (empty file)" in cap.err and "junk.png" in cap.err and "not counted" in cap.err
    text = out.read_text()
    assert "#   3 images, 32x24" in text and "mixed sizes" in text and "not counted, unreadable" in text
    _jpeg(root / "images" / "d.jpg", orientation=6)
    assert main(["new", str(root), "--out", str(tmp_path / "x.toml")]) == 2
    err = capsys.readouterr().err
    assert "d.jpg (6: rotated 90 degrees clockwise)" in err and "exiftran" in err and not (tmp_path / "x.toml").exists()


def test_the_dataset_and_mask_folders_refuse_rotated_images(tmp_path):
    """H3 through a run: the dataset task refuses a photo with an EXIF rotation (before SfM),
    the masks task a mask file with one; orientation 1 passes."""
    import io

    from pipeline import RunOptions, load_workflow, run_workflow
    from stages.registry import load_registry

    root = tmp_path / "cap"
    for i in range(4):
        _jpeg(root / "images" / f"IMG_{i}.jpg", orientation=1)
    _jpeg(root / "images" / "IMG_9.jpg", orientation=8)
    wf = tmp_path / "w.toml"
    wf.write_text('[workflow]\nnested = { object = "scene" }\n'
                  f'[axes.scene.s]\nkind = "images"\npath = "{root}"\n[axes.method.cobgs]\n[axes.object.s.cup]\n')
    out = io.StringIO()
    summary = run_workflow(load_workflow(wf, load_registry()), RunOptions(cache_dir=tmp_path / "c", only=("dataset",)),
                           stream=out)
    note = next(o.note for o in summary.outcomes.values() if o.state == "failed")
    assert "IMG_9.jpg (8: rotated 90 degrees counter-clockwise)" in note and "mogrify -auto-orient" in note, note

    from types import SimpleNamespace

    from cobgs.errors import DataError
    from cobgs.masks.sources import folder_masks as _folder_masks

    _jpeg(tmp_path / "m" / "v.jpg", orientation=3)
    with pytest.raises(DataError, match=r"v.jpg \(3: rotated 180 degrees\)"):
        _folder_masks([SimpleNamespace(name="v", width=32, height=24)], tmp_path / "m", 0)


def test_new_writes_the_recipe_that_keeps_the_boundaries(tmp_path):
    """Issue 57 item 6: no fast recipe met every target (docs/benchmarks/cost_cpu.md), so the
    workflow `cobgs new` writes trains with the paper's schedule and names the fast one in a
    comment a user can switch to."""
    from pipeline import Plan, load_workflow
    from stages.registry import load_registry

    root = tmp_path / "cap"
    for i in range(12):
        _png(root / "images" / f"{i:03d}.png")
    _png(root / "masks" / "mug" / "000.png")
    out = tmp_path / "w.toml"
    assert main(["new", str(root), "--out", str(out)]) == 0
    text = out.read_text()
    assert 'recipe = "3dgs"\n' in text and '# Faster: recipe = "fast"' in text
    train = next(t for t in Plan(load_workflow(out, load_registry())).tasks if t.stage.name == "train")
    assert train.params.value.recipe == "3dgs" and train.params.value.iterations == 30_000
