"""Scene layouts behind one registry (issue 58 item 3): a new layout is its reader module and one
line of ``cobgs.data.formats.FORMATS``; detection, ``read_scene``, the dataset kinds and the
stages read it there, and no layout is special-cased elsewhere."""

from __future__ import annotations

import io
import shutil
from pathlib import Path

import pytest

from cobgs.data.formats import FORMATS, SceneFormat, detect

HERE = Path(__file__).resolve().parent


def read_mine(path, downscale=1.0, test_every=8, test_names=None):
    """The reader of a made-up layout: a ``MINE`` file beside a transforms.json scene in ``inner/``."""
    from cobgs.data.transforms import read_transforms

    scene = read_transforms(Path(path) / "inner", downscale=downscale, test_every=test_every, test_names=test_names)
    scene.kind = "mine"
    return scene


def test_a_new_layout_is_its_reader_and_one_registry_line(tmp_path, monkeypatch):
    from cobgs.data.readers import read_scene
    from cobgs.data.synth.scene import generate_scene
    from pipeline import RunOptions, entries, load_workflow, run_workflow
    from stages.commands.new import detect as new_detect
    from stages.registry import load_registry

    monkeypatch.syspath_prepend(str(HERE))
    monkeypatch.setitem(FORMATS, "mine", SceneFormat(  # the one line
        "mine", lambda r: (r / "MINE").is_file(), "a MINE file found", f"{__name__}:read_mine", scene_type="360"))
    root = tmp_path / "cap"
    generate_scene(root / "inner", "demo", seed=0, num_views=8, width_px=64, height_px=48, workers=1, progress=False)
    (root / "MINE").write_text("")
    shutil.copytree(root / "inner" / "images", root / "images")  # (the folder SfM would read)
    assert detect(root) == "mine"
    scene = read_scene(root, test_every=4)
    assert scene.kind == "mine" and len(scene.views) == 8 and scene.test
    assert new_detect(root)["kind"] == "mine"  # `cobgs new` finds it too
    wf = tmp_path / "w.toml"
    wf.write_text(f'[workflow]\nnested = {{ object = "scene" }}\n[params.sfm]\nmode = "never"\n'
                  f'[axes.scene.cap]\nkind = "mine"\npath = "{root}"\n[axes.method.cobgs]\n[axes.object.cap.ball]\n')
    out = io.StringIO()
    w = load_workflow(wf, load_registry())
    summary = run_workflow(w, RunOptions(cache_dir=tmp_path / "c", only=("dataset",)), stream=out)
    assert summary.exit_code == 0, out.getvalue()
    import json

    rec = next(r for r in entries(w, tmp_path / "c") if r.stage == "dataset")
    spec = json.loads((rec.output("dataset") / "dataset.json").read_text())
    assert spec["kind"] == "mine" and spec["reader"]["format"] == "mine" and spec["scene_type"] == "360"
    assert "ball" in spec["objects"] and spec["protocol"] == "exact"


def test_what_sets_a_layout_apart_is_in_its_entry():
    assert list(FORMATS) == ["blender", "transforms", "colmap", "llff"]  # the detection order
    b = FORMATS["blender"]
    assert b.own_split and b.composited and b.alpha_object == "object" and not b.images_folder
    assert FORMATS["llff"].integer_downscale and not FORMATS["transforms"].own_split
    from cobgs.errors import DataError

    with pytest.raises(DataError, match="carry their own test split"):
        b.read("/nowhere", test_names=["r_0"])
    with pytest.raises(DataError, match="llff downscale must be an integer"):
        FORMATS["llff"].read("/nowhere", downscale=2.5)
