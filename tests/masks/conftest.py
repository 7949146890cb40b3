"""Stand-in model folders (built once per session) and small frame sequences."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from . import fakes, scenes


@pytest.fixture(scope="session")
def models_dir(tmp_path_factory) -> Path:
    """SAM2.1-style video export + Grounding DINO, contract names."""
    root = tmp_path_factory.mktemp("models")
    fakes.build_sam2(root)
    fakes.build_gdino(root)
    return root


@pytest.fixture(scope="session")
def models_v20(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("models_v20")
    fakes.build_sam2(root, v21=False)
    return root


@pytest.fixture(scope="session")
def models_image_only(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("models_image_only")
    fakes.build_sam2(root, video=False)
    return root


RENAMES = {
    "image": "pixel_values", "vision_feats": "image_embeddings", "vision_pos_embed": "pe",
    "high_res_feats_0": "feat_s0", "high_res_feats_1": "feat_s1",
    "image_embed": "emb", "point_coords": "coords", "point_labels": "labels",
    "low_res_masks": "masks", "iou_predictions": "scores", "obj_ptr": "pointer",
    "object_score_logits": "occlusion", "curr": "x", "memory": "mem",
    "obj_ptr_tokens": "ptr", "pix_feat_with_mem": "y", "pix_feat": "feat",
    "mask_for_mem": "m", "maskmem_features": "mf", "maskmem_pos_enc": "mp",
}


@pytest.fixture(scope="session")
def models_renamed(tmp_path_factory) -> Path:
    """Same behaviour as ``models_dir`` but every tensor renamed and outputs reordered."""
    root = tmp_path_factory.mktemp("models_renamed")
    fakes.build_sam2(root, rename=RENAMES, reverse_outputs=True)
    return root


@pytest.fixture
def scratch_models(tmp_path, models_dir) -> Path:
    """A private copy of the standard folder that a test may break."""
    dst = tmp_path / "models"
    shutil.copytree(models_dir, dst)
    return dst


@pytest.fixture(scope="session")
def red_green(tmp_path_factory):
    """15 frames: red square (0-4), absent (5-9), green square (10-14); (paths, gts)."""
    return scenes.write_sequence(tmp_path_factory.mktemp("seq"), scenes.red_gone_green())
