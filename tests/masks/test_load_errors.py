"""Every load-time check names the file, the tensor, what was expected and what was found."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from cobgs.errors import ModelError
from cobgs.masks.gdino import GroundingDino
from cobgs.masks.manifest import ModelsNotConfiguredError, load_manifest
from cobgs.masks.sam2_models import Sam2Models

from . import fakes


def _load_sam2(root):
    return Sam2Models(load_manifest(root).sam2)


def test_standard_folder_loads_and_logs_providers(models_dir, caplog):
    caplog.set_level("INFO", logger="cobgs.masks")
    models = _load_sam2(models_dir)
    assert models.has_video
    assert set(models.sessions) == {"image_encoder", "mask_decoder", "memory_attention",
                                    "memory_encoder"}
    for s in models.sessions.values():
        assert "CPUExecutionProvider" in s.providers
    assert "session runs on" in caplog.text and "requested providers" in caplog.text


@pytest.mark.parametrize("case", ["none", "missing_dir", "no_manifest"])
def test_models_not_configured(tmp_path, case):
    arg = {"none": None, "missing_dir": tmp_path / "nope", "no_manifest": tmp_path}[case]
    with pytest.raises(ModelsNotConfiguredError, match="export-onnx|does not exist|manifest"):
        load_manifest(arg)


def test_missing_graph_file_named(scratch_models):
    (scratch_models / "sam2" / "sam2_memory_encoder.onnx").unlink()
    with pytest.raises(ModelError, match=r"sam2\.files\.memory_encoder.*sam2_memory_encoder"):
        load_manifest(scratch_models)


def test_wrong_tensor_name_lists_graph_names(scratch_models):
    fakes.edit_manifest(scratch_models, lambda d: d["sam2"]["io"]["mask_decoder"].update(
        {"point_coords": "coords"}))
    with pytest.raises(ModelError) as err:
        _load_sam2(scratch_models)
    msg = str(err.value)
    assert "sam2_mask_decoder.onnx" in msg and "'coords'" in msg and "point_coords" in msg
    assert "image_embed" in msg  # the graph's actual input names are listed


def test_unknown_io_name_rejected(scratch_models):
    fakes.edit_manifest(scratch_models, lambda d: d["sam2"]["io"]["mask_decoder"].update(
        {"points": "point_coords"}))
    with pytest.raises(ModelError, match=r"unknown tensor name\(s\) \['points'\]"):
        load_manifest(scratch_models)


def test_dtype_mismatch(tmp_path):
    fakes.build_sam2(tmp_path, label_dtype=torch.int64)
    with pytest.raises(ModelError, match=r"input 'point_labels': expected dtype float32, "
                                         r"found int64"):
        _load_sam2(tmp_path)


def test_fixed_dim_mismatch(scratch_models):
    fakes.edit_manifest(scratch_models, lambda d: d["sam2"]["shape"]["image_encoder"].update(
        {"high_res_feats_0": [1, 64, 256, 256]}))
    with pytest.raises(ModelError) as err:
        _load_sam2(scratch_models)
    msg = str(err.value)
    assert "sam2_image_encoder.onnx" in msg and "high_res_feats_0" in msg
    assert "[1, 64, 256, 256]" in msg and "[1, 32, 256, 256]" in msg


def test_rank_mismatch(scratch_models):
    fakes.edit_manifest(scratch_models, lambda d: d["sam2"]["shape"]["mask_decoder"].update(
        {"object_score_logits": [1]}))
    with pytest.raises(ModelError, match=r"object_score_logits'.*expected rank 1.*found rank 2"):
        _load_sam2(scratch_models)


def test_memory_axes_must_be_dynamic(tmp_path):
    fakes.build_sam2(tmp_path, fixed_memory=True)
    with pytest.raises(ModelError, match=r"memory_attention: input 'memory'.*must be dynamic "
                                         r"\(4096\*M\), found fixed size 8192"):
        _load_sam2(tmp_path)


def test_undeclared_graph_input(scratch_models):
    # declare the SAM2.0-without-pointers layout while the graph still has pointer inputs
    fakes.edit_manifest(scratch_models, lambda d: d["sam2"]["layout"].update(ptr_mode="none"))
    with pytest.raises(ModelError, match=r"graph input\(s\) \['obj_ptr_tokens', 'obj_ptr_pos'\]"
                                         r" are not in the contract"):
        _load_sam2(scratch_models)


@pytest.mark.parametrize("key,bad", [("maskmem_tpos_enc", None),
                                     ("no_mem_embed", np.zeros((1, 256), np.float32)),
                                     ("obj_ptr_tpos_proj_weight", None)])
def test_constants_checked(scratch_models, key, bad):
    path = scratch_models / "sam2" / "sam2_constants.npz"
    data = dict(np.load(path))
    if bad is None:
        data.pop(key)
    else:
        data[key] = bad
    np.savez(path, **data)
    with pytest.raises(ModelError, match=f"sam2_constants: .*'{key}'"):
        _load_sam2(scratch_models)


@pytest.mark.parametrize("edit,match", [
    (lambda d: d["sam2"]["layout"].update(curr_layout="chw"), r"curr_layout: expected"),
    (lambda d: d["sam2"]["layout"].update(decoder_mask_planes=2), r"decoder_mask_planes"),
    (lambda d: d["sam2"]["layout"].update(bogus=1), r"unknown field\(s\) \['bogus'\]"),
    (lambda d: d["sam2"]["sam2_config"].update(num_maskmem="7"), r"num_maskmem: expected int"),
    (lambda d: d.update(version=2), r"version: expected 1"),
    (lambda d: d["sam2"]["files"].pop("constants"), r"missing 'constants'"),
    (lambda d: d["groundingdino"]["gdino"].update(text_mask_on_host=False),
     r"text_mask_on_host: only graphs that take the host-built"),
    (lambda d: d["groundingdino"]["preprocess"].update(resize="letterbox"),
     r"resize: expected 'stretch' or 'keep_aspect'"),
    (lambda d: d["sam2"]["preprocess"].update(resize="keep_aspect"),
     r"sam2.preprocess.resize: SAM2 takes every frame stretched to 1024x1024"),
])
def test_manifest_fields_validated(scratch_models, edit, match):
    fakes.edit_manifest(scratch_models, edit)
    with pytest.raises(ModelError, match=match):
        load_manifest(scratch_models)


def test_broken_json(scratch_models):
    (scratch_models / "manifest.json").write_text("{not json")
    with pytest.raises(ModelError, match="cannot read manifest"):
        load_manifest(scratch_models)


def test_gdino_traced_size_must_match_manifest(tmp_path):
    fakes.build_gdino(tmp_path, hw=(48, 64), manifest_hw=(48, 64))
    fakes.edit_manifest(tmp_path, lambda d: d["groundingdino"]["preprocess"].update(
        size=[96, 128]))
    # the manifest's declared input shape also says 48x64 -> update it like a careless user
    fakes.edit_manifest(tmp_path, lambda d: d["groundingdino"]["shape"]["model"].update(
        img=[1, 3, "*", "*"]))
    with pytest.raises(ModelError, match=r"traced at 48x64 but the manifest's "
                                         r"preprocess.size is \[96, 128\]"):
        GroundingDino(load_manifest(tmp_path).gdino)


def test_gdino_int64_mask_rejected(tmp_path):
    fakes.build_gdino(tmp_path, mask_dtype=torch.int64)
    with pytest.raises(ModelError, match=r"input 'attention_mask': expected dtype bool, "
                                         r"found int64"):
        GroundingDino(load_manifest(tmp_path).gdino)


def test_unavailable_provider_named(models_dir, caplog):
    from cobgs.masks.session import SessionOptions

    with pytest.raises(ModelError, match=r"\['NoSuchExecutionProvider'\] not available"):
        Sam2Models(load_manifest(models_dir).sam2,
                   SessionOptions(providers=["NoSuchExecutionProvider"]))
    # with a fallback listed, the missing one is dropped and said so
    caplog.set_level("WARNING", logger="cobgs.masks")
    m = Sam2Models(load_manifest(models_dir).sam2,
                   SessionOptions(providers=["NoSuchExecutionProvider", "CPUExecutionProvider"]))
    assert m.sessions["mask_decoder"].providers == ["CPUExecutionProvider"]
    assert "lacks ['NoSuchExecutionProvider']" in caplog.text


def test_manifest_json_round_trip(models_dir):
    data = json.loads((models_dir / "manifest.json").read_text())
    assert data["format"] == "cobgs-onnx-models" and set(data) >= {"sam2", "groundingdino"}
    m = load_manifest(models_dir)
    assert m.sam2.layout.ptr_mode == "separate" and m.gdino.preprocess.size_hw == (48, 64)
