"""`cobgs new FOLDER`: the layout it detects, the workflow it writes (which loads), and the
clear refusals (loose photos, no masks and no prompt, an existing file)."""

from __future__ import annotations

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
    ({"images/a.png": 1, "sparse/0/cameras.txt": 0}, "colmap"),
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
    plan = _load(out, {"COBGS_MODELS_DIR": str(tmp_path / "models")})
    assert {t.item.id for t in plan.tasks if t.stage.name == "masks"} == {"cap/a red mug", "cap/spoon"}


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
