"""Stage params are the library's own config classes (cobgs/configs/, torch-free):
checked where they are set, and importing the stages or building the CLI imports no torch."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest


def test_stage_modules_and_the_cli_import_without_torch():
    """`cobgs --help`, `cobgs status` and a cached `cobgs run` import every stage module and
    build the CLI parser: none of that may import torch (or numpy, OpenCV, pycolmap)."""
    code = ("import sys; from stages.registry import load_registry; load_registry(); "
            "from stages.commands.cli import build_parser; build_parser(); "
            "import pipeline, cobgs.configs; "
            "bad = [m for m in ('torch', 'numpy', 'cv2', 'pycolmap') if m in sys.modules]; "
            "print(','.join(bad))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


def test_stage_params_are_the_library_configs():
    """One definition of every config: the stages declare the library's classes."""
    from cobgs import configs
    from stages.masks import MasksParams
    from stages.refine import RefineParams
    from stages.registry import load_registry
    from stages.sfm import SfmParams

    graph = load_registry().graph()
    assert graph.stages["train"].params is configs.TrainConfig
    import typing

    hints = {c: typing.get_type_hints(c) for c in (RefineParams, MasksParams, SfmParams)}
    assert hints[RefineParams]["sa3d"] is configs.SA3DConfig
    assert hints[RefineParams]["flashsplat"] is configs.FlashSplatConfig
    assert hints[MasksParams]["two_stage"] is configs.TwoStageConfig
    assert hints[MasksParams]["scribbles"] is configs.ScribbleConfig
    assert hints[MasksParams]["noise"] is configs.MaskNoiseParams
    assert hints[SfmParams]["options"] is configs.SfmOptions
    from cobgs.configs import RefineConfig
    from cobgs.configs import TrainConfig

    assert RefineConfig is configs.RefineConfig and TrainConfig is configs.TrainConfig  # re-exported


def test_refine_params_are_exactly_the_methods_sections():
    """Issue 58: the refine stage's params are the union of the registered methods' sections
    (with their config classes) plus what every method reads; a method's key holds its own
    sections only: changing any other section leaves it unchanged, changing its own does not."""
    import dataclasses
    import typing

    from cobgs.refine.methods import REGISTRY, RefineMethod, SECTIONS
    from stages.refine import STAGE, RefineParams

    hints = typing.get_type_hints(RefineParams)
    assert [f.name for f in dataclasses.fields(RefineParams)] == [*RefineMethod.COMMON, *SECTIONS]
    for m in REGISTRY.values():
        for sec in m.sections:
            cls = m.config_class if len(m.sections) == 1 else typing.get_type_hints(m.config_class)[sec]
            assert hints[sec] is cls, (m.name, sec)
    changed = {"cobgs": {"delta": 0.61}, "sa3d": {"lr": 0.5}, "flashsplat": {"background_bias": 0.3},
               "ngs": {"max_points": 99}, "ludvig": {"threshold_k": 60.0}}
    assert set(changed) == set(SECTIONS)
    for m in REGISTRY.values():
        base = RefineParams(method=m.name)
        key = STAGE.key_params(base, _params_json(base))
        assert key["method"] == m.name and set(key) == {"method", "scene_type", *m.sections}
        for sec, edit in changed.items():
            p = dataclasses.replace(base, **{sec: dataclasses.replace(getattr(base, sec), **edit)})
            other = STAGE.key_params(p, _params_json(p))
            assert (other == key) == (sec not in m.sections), (m.name, sec)


def test_the_checks_options_leave_the_key_while_the_check_is_off():
    """The object check's own options (its keep rule, its edge band) say nothing of a run
    without the check: a faithful row (object_check off) and the no-split row (which forces it
    off) keep their keys whatever the options hold, so changing the default rule recomputes only
    the rows that run the check."""
    import dataclasses

    from stages.refine import STAGE, RefineParams

    def key(method, **cobgs):
        base = RefineParams(method=method)
        p = dataclasses.replace(base, cobgs=dataclasses.replace(base.cobgs, **cobgs))
        return STAGE.key_params(p, _params_json(p))

    for rule in ("votes", "iou"):
        assert key("cobgs", object_check="off", object_check_rule=rule, object_check_edge_px=3) == \
            key("cobgs", object_check="off")
        assert key("nosplit", object_check_rule=rule) == key("nosplit", object_check="off", object_check_rule="votes")
        assert key("ngs", object_check="off", object_check_rule=rule) == key("ngs", object_check="off")
    assert key("cobgs", object_check_rule="votes") != key("cobgs", object_check_rule="iou")
    assert key("cobgs", object_check="visible", object_check_rule="votes") != key("cobgs", object_check="visible")
    assert key("ngs", object_check="visible", object_check_rule="votes") != key("ngs", object_check="visible")


def _params_json(p) -> dict:
    from pipeline.params import to_json

    return to_json(p)


@pytest.mark.parametrize("sets, message", [
    (["refine.cobgs.scene_type=360"], "set refine.scene_type"),
    (["sfm.options.device=cuda"], "workflow's device"),
])
def test_fields_the_stage_sets_are_refused_as_params(tmp_path, sets, message):
    from pipeline import WorkflowError

    with pytest.raises(WorkflowError, match=message):
        _load(tmp_path, '[axes.scene.s]\nkind = "synthetic"\n', sets)


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
    (["train.iterations=-5"], "--set: train.iterations", "iterations must be in [1, 1e7]"),
    (["refine.cobgs.delta=-2"], "--set: refine.cobgs.delta", "delta must be in [0, 1]"),
    (["dataset.preset=nope"], "--set: dataset.preset", "preset must be one of"),
    (["sfm.options.camera_model=FISHEYEZ"], "--set: sfm.options.camera_model", "not a COLMAP camera model"),
    (["segment.mask_threshold=7"], "--set: segment.mask_threshold", "must be in (0, 1)"),
    ([], "w.toml: params.train.iterations", "iterations must be in [1, 1e7]"),
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


def test_masks_cache_key_holds_only_what_the_route_reads():
    """Tuning the text route (two_stage) or the noise never recomputes dataset-file masks;
    the noisy route's key follows its noise params; every route names its source."""
    from dataclasses import replace

    from pipeline.params import to_json
    from stages.masks import STAGE, MasksParams
    from cobgs.configs import MaskNoiseParams, TwoStageConfig

    def key(p):
        return STAGE.key_params(p, to_json(p))

    files = MasksParams(source="files")
    assert key(files) == key(replace(files, two_stage=TwoStageConfig(stage2_backward=True),
                                     noise=MaskNoiseParams(seed=9), intra_op_threads=3))
    assert key(files) != key(replace(files, files_threshold=10))
    noisy = MasksParams(source="noisy")
    assert key(noisy) != key(replace(noisy, noise=MaskNoiseParams(seed=9)))
    assert key(noisy) == key(replace(noisy, two_stage=TwoStageConfig(empty_rule="union")))
    assert key(files)["source"] == "files" and "two_stage" not in key(files)
    assert set(key(noisy)) == {"source", "files_threshold", "files_root", "noise"}


DEMO_WORKFLOW = Path(__file__).resolve().parents[2] / "workflows" / "demo.toml"


@pytest.mark.parametrize("key", ["train.iterations", "train.position_lr_init"])
@pytest.mark.parametrize("digits", [401, 5000])
def test_huge_numbers_are_refused_like_any_out_of_range_value(key, digits):
    """Issue 44 M1: an integer too large for a float (OverflowError in check_params /
    coerce) or past Python's digit limit (ValueError in the TOML reader) crashed the plan."""
    from pipeline import Plan, WorkflowError, load_workflow
    from stages.registry import load_registry

    value = "1" + "0" * (digits - 1)
    with pytest.raises(WorkflowError) as err:
        Plan(load_workflow(DEMO_WORKFLOW, load_registry(), [f"{key}={value}"]))
    text = str(err.value)
    assert "--set" in text and key in text and len(text) < 400, text


def test_a_huge_number_in_a_workflow_file_names_the_file(tmp_path):
    from pipeline import WorkflowError, load_workflow
    from stages.registry import load_registry

    for digits, what in ((401, "TrainConfig.iterations must be in"), (5000, "invalid value")):
        f = tmp_path / f"big{digits}.toml"
        f.write_text(f'[workflow]\nname = "big"\nnested = {{ object = "scene" }}\n[params.train]\niterations = 1{"0" * (digits - 1)}\n'
                     '[axes.scene.s]\nkind = "synthetic"\n[axes.method.cobgs]\n[axes.object.s.ball]\n')
        with pytest.raises(WorkflowError) as err:
            from pipeline import Plan

            Plan(load_workflow(f, load_registry(), []))
        assert str(f) in str(err.value) and what in str(err.value) and len(str(err.value)) < 400, str(err.value)


def test_segment_mask_threshold_range_is_stated_once_and_documented():
    """Issue 44: SegmentParams.mask_threshold was checked by hand in __post_init__ with no
    RANGES entry, so docs/pipeline.md listed no range for it."""
    from pathlib import Path

    from stages.segment import SegmentParams

    assert SegmentParams.RANGES["mask_threshold"] == "(0, 1)"
    for bad in (0.0, 1.0, float("nan")):
        with pytest.raises(ValueError, match=r"SegmentParams.mask_threshold must be in \(0, 1\)"):
            SegmentParams(mask_threshold=bad)
    docs = (Path(__file__).resolve().parents[2] / "docs" / "pipeline.md").read_text()
    assert "# mask_threshold = ...  # default: none (Optional[float]); in (0, 1)" in docs


DEMO = DEMO_WORKFLOW


@pytest.mark.parametrize("setting", [
    # H2: values that ruined results silently
    "train.prune_min_opacity=inf", "train.ssim_weight=nan", "train.position_lr_init=nan", "train.adam_eps=0",
    "train.init_opacity=1.5", "refine.cobgs.mask_lambda=nan", "refine.cobgs.split_size_fraction=nan",
    "refine.cobgs.raem_footprint_px=-1",
    # M1: errors that came late, after upstream tasks ran
    "train.position_lr_init=-1", "train.adam_eps=nan", "train.log_interval_its=0", "train.backend=evil",
    "evaluate.boundary_ratio=nan", "dataset.workers=-3", "dataset.num_views=-1", "refine.cobgs.label_name=x",
    # L7: no upper bounds
    "train.iterations=10000000000000000000", "refine.cobgs.split_children=1000000", "dataset.width_px=100000",
    # L10
    "evaluate.boundary_ratio=5", "summary.target_miou=nan", "evaluate.warn_psnr_drop_db=inf",
])
def test_params_out_of_range_refused_when_planned_naming_set_and_key(setting):
    from pipeline import Plan, WorkflowError, load_workflow
    from stages.registry import load_registry

    key = setting.split("=")[0]
    with pytest.raises(WorkflowError) as err:
        Plan(load_workflow(DEMO, load_registry(), [setting]))
    text = str(err.value)
    assert "--set" in text and key.split(".")[-1] in text, text
    assert ("must be in" in text or "must be one of" in text or "finite" in text
            or "an integer" in text), text


def test_every_numeric_param_states_a_range_or_is_finite():
    """The rule behind the list above: each float param of every stage has a stated range
    or must be finite; the generated docs list every range."""
    import dataclasses
    import typing

    from cobgs.configs import check_params
    from stages.registry import load_registry

    for stage in load_registry().stages.values():
        cls = stage.params
        if cls is None:
            continue
        todo = [cls]
        while todo:
            c = todo.pop()
            hints = typing.get_type_hints(c)
            for f in dataclasses.fields(c):
                tp = hints[f.name]
                if dataclasses.is_dataclass(tp):
                    todo.append(tp)
            # a float field holding nan is refused by every params class
            for f in dataclasses.fields(c):
                if hints[f.name] is float:
                    inst = c()
                    with pytest.raises(ValueError):
                        check_params(dataclasses.replace(inst, **{f.name: float("nan")}))


def test_docs_list_every_param_with_its_range_as_generated():
    """docs/pipeline.md states the valid range of every param, generated from the params
    classes (`cobgs stages --docs docs/pipeline.md` rewrites it), never written twice."""
    from pipeline.commands import DOCS_BEGIN, DOCS_END, stages_toml
    from stages.registry import load_registry

    doc = (Path(__file__).resolve().parents[2] / "docs" / "pipeline.md").read_text()
    inside = doc.split(DOCS_BEGIN, 1)[1].split(DOCS_END, 1)[0]
    expected = f"\n```toml\n{stages_toml(load_registry()).rstrip()}\n```\n"
    assert inside == expected, "docs/pipeline.md is stale: run `cobgs stages --docs docs/pipeline.md`"
    assert "prune_min_opacity = 0.005  # in [0, 1)" in inside and "boundary_ratio = 0.02  # in (0, 0.5]" in inside


def test_docs_target_that_is_missing_or_has_no_markers_is_named(tmp_path):
    """`cobgs stages --docs FILE`: a missing file, a folder, or a file without the markers is
    one clear error naming it; the file is left as it was."""
    from pipeline.commands import DOCS_BEGIN, DOCS_END, write_params_docs
    from pipeline.errors import PipelineError

    for target in (tmp_path / "missing.md", tmp_path):
        with pytest.raises(PipelineError, match="cannot read it.*--docs takes an existing Markdown file"):
            write_params_docs(target, "[params.x]\n")
    plain = tmp_path / "plain.md"
    plain.write_text("# no markers\n")
    with pytest.raises(PipelineError, match="no .* markers"):
        write_params_docs(plain, "[params.x]\n")
    assert plain.read_text() == "# no markers\n"
    good = tmp_path / "good.md"
    good.write_text(f"a\n{DOCS_BEGIN}\nold\n{DOCS_END}\nb\n")
    assert write_params_docs(good, "[params.x]\ny = 1\n") == 1
    assert good.read_text() == f"a\n{DOCS_BEGIN}\n```toml\n[params.x]\ny = 1\n```\n{DOCS_END}\nb\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["good.md", "plain.md"]  # no temporaries left
