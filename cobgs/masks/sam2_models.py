"""The SAM2 export: its 2 or 4 checked sessions, its constants, and layout adapters.

Everything here speaks the contract's layout; the manifest's layout flags are undone at
this boundary so the video logic never sees them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Optional, Tuple

import numpy as np

from cobgs.errors import ModelError

from cobgs.masks.manifest import Sam2Manifest
from cobgs.masks.session import GraphSession, SessionOptions

VIDEO_REFUSED = (
    "this SAM2 export is image-only (no memory_attention / memory_encoder graphs), so it "
    "can segment a prompted frame but cannot propagate to other frames; export the full "
    "video model with `cobgs export-onnx sam2 ...`"
)


@dataclass
class EncodedFrame:
    """Image-encoder outputs of one frame (the raw features, without no_mem_embed).

    Attributes:
        feats: float32 [1, 256, 64, 64].
        pos: float32 [1, 256, 64, 64].
        hr0: float32 [1, 32, 256, 256].
        hr1: float32 [1, 64, 128, 128].
    """

    feats: np.ndarray
    pos: np.ndarray
    hr0: np.ndarray
    hr1: np.ndarray
    _tokens: Optional[Tuple[np.ndarray, np.ndarray]] = None

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in (self.feats, self.pos, self.hr0, self.hr1))

    def tokens(self) -> Tuple[np.ndarray, np.ndarray]:
        """(curr, curr_pos) as float32 [4096, 1, 256] token sequences (row-major h, w),
        computed once per frame: every object and pass tracking the frame reuses them."""
        if self._tokens is None:
            self._tokens = (_token_major(self.feats)[:, None, :],
                            _token_major(self.pos)[:, None, :])
        return self._tokens


@dataclass
class Decoded:
    """Mask-decoder outputs for one frame and one object.

    Attributes:
        masks: float32 [planes, 256, 256] logits before no-object gating.
        ious: float32 [planes].
        obj_ptr: float32 [planes, 256] or None when the export has no pointer output.
        object_score: the object-score logit (> 0: object present).
    """

    masks: np.ndarray
    ious: np.ndarray
    obj_ptr: Optional[np.ndarray]
    object_score: float


def _token_major(x: np.ndarray) -> np.ndarray:
    """[1, C, H, W] -> contiguous [H*W, C] (cv2's transpose: ~100x numpy's strided copy)."""
    import cv2

    c = x.shape[1]
    return cv2.transpose(np.ascontiguousarray(x, np.float32).reshape(c, -1))


def _load_constants(path, layout, config) -> Dict[str, np.ndarray]:
    try:
        with np.load(path) as z:
            data = {k: np.asarray(z[k], np.float32) for k in z.files}
    except (OSError, ValueError) as exc:
        raise ModelError(f"cannot read SAM2 constants: {exc}", path) from exc
    need = {"maskmem_tpos_enc": (config.num_maskmem, 1, 1, config.mem_dim)}
    if not layout.encoder_feat_has_no_mem_embed:
        need["no_mem_embed"] = (1, 1, config.hidden_dim)
    elif "no_mem_embed" in data:
        need["no_mem_embed"] = (1, 1, config.hidden_dim)
    if config.add_tpos_enc_to_obj_ptrs and config.proj_tpos_enc_in_obj_ptrs:
        need["obj_ptr_tpos_proj_weight"] = (config.mem_dim, config.hidden_dim)
        need["obj_ptr_tpos_proj_bias"] = (config.mem_dim,)
    optional = {
        "no_obj_embed_spatial": (1, config.mem_dim),
        "mask_downsample_weight": (1, 1, 4, 4),
        "mask_downsample_bias": (1,),
    }
    for key, shape in {**need, **optional}.items():
        if key not in data:
            if key in need:
                raise ModelError(
                    f"sam2_constants: expected array '{key}' of shape {list(shape)}, found "
                    f"none; arrays present: {sorted(data)}",
                    path,
                )
            continue
        if data[key].shape != shape:
            raise ModelError(
                f"sam2_constants: '{key}': expected shape {list(shape)}, found "
                f"{list(data[key].shape)}",
                path,
            )
    if layout.encoder_feat_has_no_mem_embed and "no_mem_embed" not in data:
        raise ModelError(
            "sam2_constants: the encoder adds no_mem_embed (layout flag), so the host needs "
            "'no_mem_embed' [1,1,256] to recover the raw features for memory; found none",
            path,
        )
    return data


class Sam2Models:
    """Sessions and constants of one SAM2 export.

    Args:
        manifest: the ``sam2`` part of a loaded manifest.
        options: providers / threads / tracing for every session.
    """

    def __init__(self, manifest: Sam2Manifest, options: Optional[SessionOptions] = None):
        self.manifest = manifest
        self.layout = manifest.layout
        self.config = manifest.config
        self.preprocess = manifest.preprocess
        self.constants = _load_constants(manifest.constants_path, self.layout, self.config)
        self.sessions: Dict[str, GraphSession] = {
            key: GraphSession(spec, options) for key, spec in manifest.graphs.items()
        }
        c = self.constants
        self.no_mem_embed = c["no_mem_embed"].reshape(1, -1, 1, 1) if "no_mem_embed" in c else None
        self.tpos_enc = c["maskmem_tpos_enc"].reshape(self.config.num_maskmem, self.config.mem_dim)
        self.tpos_proj = (
            (c["obj_ptr_tpos_proj_weight"], c["obj_ptr_tpos_proj_bias"])
            if "obj_ptr_tpos_proj_weight" in c else None
        )
        self.no_obj_embed_spatial = c.get("no_obj_embed_spatial")

    @property
    def has_video(self) -> bool:
        return "memory_attention" in self.sessions

    def require_video(self) -> None:
        if not self.has_video:
            raise ModelError(VIDEO_REFUSED, self.manifest.constants_path.parent)

    def call_counts(self) -> Dict[str, int]:
        return {k: s.stats.calls for k, s in self.sessions.items()}

    # ------------------------------------------------------------------ graphs
    def encode(self, image: np.ndarray) -> EncodedFrame:
        """float32 [1, 3, 1024, 1024] normalised frame -> raw features."""
        out = self.sessions["image_encoder"].run({"image": image})
        feats = out["vision_feats"]
        if self.layout.encoder_feat_has_no_mem_embed:
            feats = feats - self.no_mem_embed  # memory graphs take the raw features
        return EncodedFrame(feats, out["vision_pos_embed"], out["high_res_feats_0"],
                            out["high_res_feats_1"])

    def decode(
        self,
        embed: np.ndarray,
        frame: EncodedFrame,
        coords: np.ndarray,
        labels: np.ndarray,
        mask_input: Optional[np.ndarray] = None,
    ) -> Decoded:
        """Run the mask decoder.

        Args:
            embed: float32 [1, 256, 64, 64] image embedding (features + no_mem_embed on a
                prompted frame, memory-conditioned features on a tracked frame).
            coords: float32 [N, 2] points in the 1024 frame; labels: [N] (0, 1, 2, 3, -1).
            mask_input: float32 [256, 256] dense prompt logits, or None.
        """
        if coords.shape[0] == 0:  # no prompt: one padding point, as upstream
            coords = np.zeros((1, 2), np.float32)
            labels = -np.ones((1,), np.float32)
        feeds = {
            "image_embed": embed.astype(np.float32, copy=False),
            "high_res_feats_0": frame.hr0,
            "high_res_feats_1": frame.hr1,
            "point_coords": coords.astype(np.float32)[None],
            "point_labels": labels.astype(np.float32)[None],
            "mask_input": (np.zeros((1, 1, 256, 256), np.float32) if mask_input is None
                           else mask_input.astype(np.float32).reshape(1, 1, 256, 256)),
            "has_mask_input": np.array([0.0 if mask_input is None else 1.0], np.float32),
        }
        out = self.sessions["mask_decoder"].run(feeds)
        ptr = out.get("obj_ptr")
        return Decoded(
            masks=out["low_res_masks"][0],
            ious=out["iou_predictions"][0],
            obj_ptr=None if ptr is None else ptr[0],
            object_score=float(out["object_score_logits"].reshape(-1)[0]),
        )

    def attend(self, frame: EncodedFrame, mem) -> np.ndarray:
        """Memory attention: raw features + memories -> float32 [1, 256, 64, 64]."""
        if self.layout.curr_layout == "hw1c":
            curr, curr_pos = frame.tokens()
        else:
            curr, curr_pos = frame.feats, frame.pos
        feeds = {"curr": curr, "curr_pos": curr_pos}
        mode = self.layout.ptr_mode
        if mode == "separate":
            feeds.update(memory=mem.memory, memory_pos=mem.memory_pos,
                         obj_ptr_tokens=mem.ptr_tokens, obj_ptr_pos=mem.ptr_pos)
        elif mode == "concat_memory":
            feeds.update(
                memory=np.concatenate([mem.memory, mem.ptr_tokens]),
                memory_pos=np.concatenate([mem.memory_pos, mem.ptr_pos]),
                num_obj_ptr_tokens=np.array([mem.ptr_tokens.shape[0]], np.int64),
            )
        else:
            feeds.update(memory=mem.memory, memory_pos=mem.memory_pos)
        return self.sessions["memory_attention"].run(feeds)["pix_feat_with_mem"]

    def encode_memory(self, frame: EncodedFrame, mask_for_mem: np.ndarray,
                      object_score: float):
        """Memory encoder -> (features [4096, 64], pos [4096, 64]), tokens row-major."""
        feeds = {"pix_feat": frame.feats,
                 "mask_for_mem": mask_for_mem.reshape(1, 1, *mask_for_mem.shape[-2:])}
        if self.layout.memenc_takes_object_score:
            feeds["object_score_logits"] = np.array([[object_score]], np.float32)
        out = self.sessions["memory_encoder"].run(feeds)
        feats = _token_major(out["maskmem_features"])
        if not self.layout.memenc_takes_object_score and self.no_obj_embed_spatial is not None:
            if object_score <= 0:  # SAM2.1 marks frames without the object
                feats = feats + self.no_obj_embed_spatial
        return feats, _token_major(out["maskmem_pos_enc"])
