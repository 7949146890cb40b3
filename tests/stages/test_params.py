"""The stages' params mirror the library configs exactly (stages/params.py says why)."""

from __future__ import annotations

import dataclasses
import importlib
import subprocess
import sys

import pytest

from stages.params import MIRRORS, to_config


def _norm(annotation) -> str:
    """Annotations as text, typing aliases spelled like the builtins (Tuple -> tuple)."""
    text = str(annotation)
    for alias in ("Tuple", "List", "Dict"):
        text = text.replace(alias + "[", alias.lower() + "[")
    return text


@pytest.mark.parametrize("mirror", list(MIRRORS), ids=lambda m: m.__name__)
def test_mirror_matches_library(mirror):
    module, name, left_out = MIRRORS[mirror]
    lib = getattr(importlib.import_module(module), name)
    lib_fields = {f.name: f for f in dataclasses.fields(lib) if f.name not in left_out}
    ours = {f.name: f for f in dataclasses.fields(mirror)}
    assert list(ours) == list(lib_fields), f"{mirror.__name__} fields differ from {module}.{name}"
    for k, f in lib_fields.items():
        assert ours[k].default == f.default, f"{mirror.__name__}.{k}: {ours[k].default!r} != {f.default!r}"
        assert _norm(ours[k].type) == _norm(f.type), f"{mirror.__name__}.{k}: type {ours[k].type} != {f.type}"
    # and the conversion builds the library object with the same values
    cfg = to_config(mirror(), lib)
    assert all(getattr(cfg, k) == v for k, v in dataclasses.asdict(mirror()).items())


def test_stage_modules_import_without_torch():
    """`cobgs status` / a cached `cobgs run` import every stage module: keep torch out."""
    code = ("import sys; from stages.registry import load_registry; load_registry(); "
            "bad = [m for m in ('torch', 'numpy', 'cv2', 'pycolmap') if m in sys.modules]; "
            "print(','.join(bad))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


def _load(tmp_path, text, sets=()):
    from pipeline import Plan, load_workflow
    from stages.registry import load_registry

    path = tmp_path / "w.toml"
    path.write_text('[workflow]\nnested = { object = "scene" }\n' + text
                    + '[axes.method.cobgs]\n[axes.object.s.ball]\n')
    return path, Plan(load_workflow(path, load_registry(), list(sets)))


@pytest.mark.parametrize("text, sets, where", [
    ('[params.refine]\nmethod = "cobgss"\n[axes.scene.s]\nkind = "synthetic"\n', (),
     "w.toml: params.refine.method: "),
    ('[axes.scene.s]\nkind = "synthetic"\n', ("refine.method=x",), "--set: refine.method: "),
    ('[params.dataset]\ndownscale = -1.0\n[axes.scene.s]\nkind = "synthetic"\n', (),
     "w.toml: params.dataset.downscale: "),
])
def test_a_refused_value_names_its_file_and_key(tmp_path, text, sets, where):
    """A value a params class refuses is reported with the file (or --set) and the dotted
    key that set it, before any task runs."""
    from pipeline import WorkflowError

    with pytest.raises(WorkflowError) as info:
        _load(tmp_path, text, sets)
    assert where in str(info.value), str(info.value)


def test_kind_images_without_an_images_folder_is_refused_at_load(tmp_path):
    from pipeline import WorkflowError

    (tmp_path / "photos").mkdir()
    (tmp_path / "photos" / "IMG_1.jpg").write_bytes(b"")
    with pytest.raises(WorkflowError) as info:
        _load(tmp_path, f'[axes.scene.s]\nkind = "images"\npath = "{tmp_path / "photos"}"\n')
    text = str(info.value)
    assert "axes.scene.s.path" in text and "no images/ subfolder" in text and "IMG_1.jpg" in text


@pytest.mark.parametrize("sets, where, message", [
    (["train.iterations=-5"], "--set: train.iterations", "iterations must be >= 1"),
    (["refine.cobgs.delta=-2"], "--set: refine.cobgs.delta", "delta must be in [0, 1]"),
    (["dataset.preset=nope"], "--set: dataset.preset", "preset must be one of"),
    (["sfm.options.camera_model=FISHEYEZ"], "--set: sfm.options.camera_model", "not a COLMAP camera model"),
    (["segment.mask_threshold=7"], "--set: segment.mask_threshold", "must be in (0, 1)"),
    ([], "w.toml: params.train.iterations", "iterations must be >= 1"),
])
def test_bad_values_stop_the_run_before_any_task(tmp_path, sets, where, message):
    """Values only the library can judge (TrainConfig, RefineConfig, SfmOptions and
    pycolmap's camera models, the generator's presets) stop `cobgs run` before the first
    task, naming the file (or --set) and the key; nothing is written to the cache."""
    from pipeline import RunOptions, WorkflowError, load_workflow, run_workflow
    from stages.registry import load_registry

    path = tmp_path / "w.toml"
    path.write_text('[workflow]\nnested = { object = "scene" }\n'
                    + ("" if sets else "[params.train]\niterations = -5\n")
                    + '[axes.scene.s]\nkind = "synthetic"\n[axes.method.cobgs]\n[axes.object.s.ball]\n')
    wf = load_workflow(path, load_registry(), sets)
    with pytest.raises(WorkflowError) as info:
        run_workflow(wf, RunOptions(cache_dir=tmp_path / "cache"))
    text = str(info.value)
    assert where in text and message in text, text
    assert not (tmp_path / "cache" / "entries").exists() or not any((tmp_path / "cache" / "entries").iterdir())
