"""Issue 56: what cannot succeed is refused before the hours of SfM and training, and no
rotated mask is ever served. Each test reproduces the report's steps through the command line
(`cobgs synth`, `cobgs new`, `cobgs run`) or the workflow loader."""

from __future__ import annotations

import io
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline import RunOptions, WorkflowError, load_workflow, run_workflow
from stages.commands.cli import main
from stages.registry import load_registry

REPO = Path(__file__).resolve().parents[2]


def _cli(*args, cwd=REPO, env=None):
    return subprocess.run([sys.executable, "-m", "stages.commands.cli", *map(str, args)], cwd=cwd,
                          env={**os.environ, "PYTHONPATH": str(REPO), **(env or {})}, capture_output=True,
                          text=True, timeout=600)


def _tag(path: Path, orientation: int = 6) -> None:
    """Give an image file an EXIF orientation tag (PIL writes PNG's eXIf chunk)."""
    from PIL import Image

    with Image.open(path) as im:
        im.load()
        exif = im.getexif()
        exif[0x0112] = orientation
        im.save(path, exif=exif.tobytes())


@pytest.fixture(scope="module")
def square(tmp_path_factory):
    """`cobgs synth --out sq --size 128x128 -q`, as the report reproduced it."""
    root = tmp_path_factory.mktemp("synth")
    r = _cli("synth", "--out", root / "sq", "--size", "128x128", "-q")
    assert r.returncode == 0, r.stderr
    return root / "sq"


def _photos(square: Path, out: Path) -> Path:
    """images/ and masks/ball/ copied into a folder of one's own (the layout cobgs new reads)."""
    shutil.copytree(square / "images", out / "images")
    shutil.copytree(square / "masks" / "ball", out / "masks" / "ball")
    return out


def test_a_tagged_mask_is_refused_naming_the_tag_never_rotated_and_used(square, tmp_path):
    """H1 / M11: a mask with an EXIF orientation tag in the scene's masks/<object>/ was rotated
    by SfM's undistortion (cv2's grayscale read applies the tag) and used with no word said."""
    ph = _photos(square, tmp_path / "ph")
    _tag(ph / "masks" / "ball" / "0002.png")
    r = _cli("new", ph, "--out", tmp_path / "ph.toml")
    assert r.returncode == 2 and "0002.png (6: rotated 90 degrees clockwise)" in r.stderr, r.stderr
    assert not (tmp_path / "ph.toml").exists()
    # a workflow written before the tag: the run stops at the dataset task, before SfM
    shutil.copy(square / "masks" / "ball" / "0002.png", ph / "masks" / "ball" / "0002.png")
    assert _cli("new", ph, "--out", tmp_path / "ph.toml").returncode == 0
    _tag(ph / "masks" / "ball" / "0002.png")
    cache = tmp_path / "c"
    r = _cli("run", tmp_path / "ph.toml", "--set", "train.iterations=300", "--cache-dir", cache)
    assert r.returncode == 1 and "EXIF orientation other than 1: 0002.png (6: rotated 90 degrees clockwise)" \
        in r.stdout, r.stdout[-3000:]
    assert sorted(p.name for p in (cache / "entries").iterdir()) == [] if (cache / "entries").is_dir() else True
    assert not (cache / "entries" / "sfm").exists()
    # every reader takes a mask's pixels as stored, tag or not (one reading of "up")
    import cv2

    from stages._common import read_mask_png

    m = read_mask_png(ph / "masks" / "ball" / "0002.png", 128, 128).numpy()
    stored = cv2.imread(str(square / "masks" / "ball" / "0002.png"), cv2.IMREAD_UNCHANGED) >= 128
    assert (m == stored).all()


def test_masks_not_named_after_the_photos_are_said_at_cobgs_new_and_at_the_dataset(square, tmp_path):
    """M9: cobgs new accepted masks named otherwise; the run then failed after training with a
    wrong hint. Now both say it at once, with examples of both names."""
    ph = _photos(square, tmp_path / "ph")
    assert _cli("new", ph, "--out", tmp_path / "ph.toml").returncode == 0
    for f in sorted((ph / "masks" / "ball").iterdir()):
        f.rename(f.with_name(f"mask_{f.name}"))
    r = _cli("new", ph, "--out", tmp_path / "other.toml")
    assert r.returncode == 2 and "no mask file is named after a photo" in r.stderr, r.stderr
    assert "mask_0000.png" in r.stderr and "'0000'" in r.stderr
    r = _cli("run", tmp_path / "ph.toml", "--set", "train.iterations=300", "--cache-dir", tmp_path / "c")
    assert r.returncode == 1 and "no mask file is named after a photo" in r.stdout, r.stdout[-3000:]
    assert not (tmp_path / "c" / "entries" / "sfm").exists()


def test_cobgs_new_refuses_an_empty_prompt_and_a_name_it_would_change(square, tmp_path, capsys):
    """M8 (`--prompt ""` was refused only after SfM and training) and the low item `--name ../x`
    silently written as `_x`."""
    ph = _photos(square, tmp_path / "ph")
    with pytest.raises(SystemExit) as e:
        main(["new", str(ph), "--out", str(tmp_path / "a.toml"), "--prompt", " "])
    assert e.value.code == 2 and "an empty text prompt finds nothing" in capsys.readouterr().err
    assert main(["new", str(ph), "--out", str(tmp_path / "a.toml"), "--name", "../x"]) == 2
    assert "e.g. '_x'" in capsys.readouterr().err and not (tmp_path / "a.toml").exists()


def test_a_folder_named_with_a_variable_is_written_so_that_it_loads_itself(square, tmp_path, monkeypatch):
    """M14: `cobgs new` on a folder whose name holds `${VAR}` wrote a path that, with VAR set,
    loaded another folder. `$${` is a literal `${`."""
    ph = _photos(square, tmp_path / "my${VAR}scene")
    other = _photos(square, tmp_path / "myOTHERscene")
    assert main(["new", str(ph), "--out", str(tmp_path / "w.toml")]) == 0
    monkeypatch.setenv("VAR", "OTHER")
    wf = load_workflow(tmp_path / "w.toml", load_registry())
    (scene,) = wf.axes.all_items()[0].attrs["scene"].path,
    assert Path(scene) == ph and Path(scene) != other


TINY = """
[workflow]
name = "{name}"
nested = {{ object = "scene" }}
[params.dataset]
preset = "demo"
num_views = 8
[axes.scene."{scene}"]
kind = "synthetic"
[axes.method."{method}"]
[axes.object."{scene}".ball]
{extra}
"""


def _wf(tmp_path, name="tiny", scene="tiny", method="cobgs", extra=""):
    path = tmp_path / "w.toml"
    path.write_text(TINY.format(name=name, scene=scene, method=method, extra=extra))
    return path


def test_names_that_would_break_a_report_or_an_export_are_refused_at_load(tmp_path):
    """M10 (a 300-character workflow name loaded, then the report failed with "File name too
    long"), M12 (a method named train.json, a scene named summary.json made export crash with
    NotADirectoryError) and the low item (names holding U+202E / U+FEFF)."""
    cases = [(dict(name="n" * 300), r"workflow name 'nnn.*'... is 300 bytes long; at most 100"),
             (dict(method="train.json"), r"value name 'train.json' is the name of a file cobgs writes"),
             (dict(scene="summary.json"), r"value name 'summary.json' is the name of a file cobgs writes"),
             (dict(method="evil\u202egnp.exe"), r"invisible formatting characters \(U\+202E\)"),
             (dict(name="\ufeffdemo"), r"invisible formatting character")]
    for kw, match in cases:
        with pytest.raises(WorkflowError, match=match):
            load_workflow(_wf(tmp_path, **kw), load_registry())


def _run(path, cache, sets=()):
    return run_workflow(load_workflow(path, load_registry(), list(sets)),
                        RunOptions(cache_dir=cache, package_version="test"), stream=io.StringIO())


def test_plan_time_refusals(tmp_path, monkeypatch):
    """M8: refused only after SfM and training (hours on a real capture), though knowable when
    the run is planned: a CUDA device on a CPU-only torch, a models folder without
    manifest.json, an EXIF-tagged mask in a mask_dir. Nothing runs."""
    import torch

    cache = tmp_path / "c"
    if not torch.cuda.is_available():
        with pytest.raises(WorkflowError, match=r"settings.device = 'cuda'.*this torch .* (is built without CUDA|"
                                                r"sees no CUDA device); run with --set device=cpu"):
            _run(_wf(tmp_path), cache, ["device=cuda"])
        assert not (cache / "entries").exists() or not any((cache / "entries").iterdir())
    from stages import registry as reg

    def no_gpu(device):
        raise ValueError("this torch (x) sees no CUDA device; run with --set device=cpu")

    monkeypatch.setattr(reg, "check_device", no_gpu)
    with pytest.raises(WorkflowError, match="sees no CUDA device"):
        _run(_wf(tmp_path), cache, ["device=cuda:0"])
    models = tmp_path / "models"
    models.mkdir()
    clicks = tmp_path / "clicks.json"
    clicks.write_text(json.dumps({"objects": {"ball": {"frames": {"0001": {"positive": [[10, 10]]}}}}}))
    from pipeline import Plan

    with pytest.raises(WorkflowError, match=r"no manifest.json in the model folder"):
        Plan(load_workflow(_wf(tmp_path), load_registry(), ["masks.source=points", f"masks.models_dir={models}",
                                                            f"masks.points_file={clicks}"]))
    masks = tmp_path / "released"
    masks.mkdir()
    import cv2
    import numpy as np

    for i in range(3):
        cv2.imwrite(str(masks / f"{i:04d}.png"), np.full((8, 8), 255, np.uint8))
    _tag(masks / "0001.png", 8)
    path = _wf(tmp_path, extra=f'mask_dir = "{masks}"')
    with pytest.raises(WorkflowError, match=r"0001.png \(8: rotated 90 degrees counter-clockwise\)"):
        _run(path, cache)
    assert not (cache / "entries").exists() or not any((cache / "entries").iterdir())


def test_cheap_refusals_of_the_low_items(tmp_path, capsys):
    """Issue 56 (low): a path on a synthetic scene (its fingerprint walked `/`), a report into
    the cache's tmp/, `--turntables 3000`, pycolmap's stack dump on SIGTERM."""
    with pytest.raises(WorkflowError, match="kind 'synthetic' is generated, not read: it takes no path"):
        _run(_wf(tmp_path), tmp_path / "c", ["axes.scene.tiny.path=/"])
    cache = tmp_path / "c"
    (cache / "tmp").mkdir(parents=True)
    path = _wf(tmp_path)
    assert main(["report", str(path), "--out", str(cache / "tmp" / "r"), "--cache-dir", str(cache)]) == 2
    assert "lies inside the cache folder" in capsys.readouterr().err and not (cache / "tmp" / "r").exists()
    assert main(["export", str(path), "--to", str(tmp_path), "--cache-dir", str(cache)]) == 2
    assert "holds the cache folder" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["report", str(path), "--turntables", "3000"])
    assert "from 0 (none) to 360" in capsys.readouterr().err
    code = ("import os, signal, time\nfrom cobgs.data.pycolmap_import import import_pycolmap\nimport_pycolmap()\n"
            "os.kill(os.getpid(), signal.SIGTERM)\ntime.sleep(5)\n")
    r = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert r.returncode == -15 and "stack trace" not in r.stderr and "SIGTERM" not in r.stderr, r.stderr
