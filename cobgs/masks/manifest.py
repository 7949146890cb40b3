"""``manifest.json``: what a user's model folder holds and how its tensors map onto ours.

The contract (``docs/onnx_contract.md``) fixes *our* tensor names, dtypes and shapes. A manifest
maps them onto an export's own names (``io``), may override dtypes/shapes where a layout
flag changes them, and carries the preprocessing and model constants the host needs. A
folder written by ``cobgs export-onnx`` has a manifest that maps every name onto itself.

Layout of the file::

    {"format": "cobgs-onnx-models", "version": 1,
     "sam2": {"files": {...}, "io": {graph: {ours: theirs}}, "dtype": {...}, "shape": {...},
              "layout": {...}, "preprocess": {...}, "sam2_config": {...}},
     "groundingdino": {"files": {...}, "io": {...}, "dtype": {...}, "shape": {...},
                       "preprocess": {...}, "gdino": {...}}}

Either model may be absent: the two-stage text path needs both, the point/scribble path
needs only ``sam2``.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Dict, List, Optional, Tuple, Union

from cobgs._atomic import write_text_atomic
from cobgs.errors import ModelError

MANIFEST_NAME = "manifest.json"
FORMAT = "cobgs-onnx-models"
VERSION = 1

Dim = Union[int, str]  # int: fixed size; string: a dynamic size ("*": fixed or dynamic)


class ModelsNotConfiguredError(ModelError):
    """No usable model folder was given (none set, missing, or lacking a model we need)."""


# ----------------------------------------------------------------------------------------
# The contract's tensors, per graph: (our name, dtype, shape). Strings are dynamic sizes.
# ----------------------------------------------------------------------------------------
SAM2_ENCODER_IN = {"image": ("float32", [1, 3, 1024, 1024])}
SAM2_ENCODER_OUT = {
    "vision_feats": ("float32", [1, 256, 64, 64]),
    "vision_pos_embed": ("float32", [1, 256, 64, 64]),
    "high_res_feats_0": ("float32", [1, 32, 256, 256]),
    "high_res_feats_1": ("float32", [1, 64, 128, 128]),
}
SAM2_DECODER_IN = {
    "image_embed": ("float32", [1, 256, 64, 64]),
    "high_res_feats_0": ("float32", [1, 32, 256, 256]),
    "high_res_feats_1": ("float32", [1, 64, 128, 128]),
    "point_coords": ("float32", [1, "N", 2]),
    "point_labels": ("float32", [1, "N"]),
    "mask_input": ("float32", [1, 1, 256, 256]),
    "has_mask_input": ("float32", [1]),
}
SAM2_DECODER_OUT = {
    "low_res_masks": ("float32", [1, 4, 256, 256]),
    "iou_predictions": ("float32", [1, 4]),
    "obj_ptr": ("float32", [1, 4, 256]),
    "object_score_logits": ("float32", [1, 1]),
}
SAM2_MEMATTN_IN = {
    "curr": ("float32", [4096, 1, 256]),
    "curr_pos": ("float32", [4096, 1, 256]),
    "memory": ("float32", ["4096*M", 1, 64]),
    "memory_pos": ("float32", ["4096*M", 1, 64]),
    "obj_ptr_tokens": ("float32", ["4*P", 1, 64]),
    "obj_ptr_pos": ("float32", ["4*P", 1, 64]),
}
SAM2_MEMATTN_OUT = {"pix_feat_with_mem": ("float32", [1, 256, 64, 64])}
SAM2_MEMENC_IN = {
    "pix_feat": ("float32", [1, 256, 64, 64]),
    "mask_for_mem": ("float32", [1, 1, 1024, 1024]),
    "object_score_logits": ("float32", [1, 1]),
}
SAM2_MEMENC_OUT = {
    "maskmem_features": ("float32", [1, 64, 64, 64]),
    "maskmem_pos_enc": ("float32", [1, 64, 64, 64]),
}
GDINO_IN = {
    "img": ("float32", [1, 3, "*", "*"]),  # "*": fixed or dynamic
    "input_ids": ("int64", [1, "L"]),
    "attention_mask": ("bool", [1, "L"]),
    "position_ids": ("int64", [1, "L"]),
    "token_type_ids": ("int64", [1, "L"]),
    "text_token_mask": ("bool", [1, "L", "L"]),
}
GDINO_OUT = {"logits": ("float32", [1, 900, 256]), "boxes": ("float32", [1, 900, 4])}

SAM2_GRAPHS = ("image_encoder", "mask_decoder", "memory_attention", "memory_encoder")
SAM2_FILES = {
    "image_encoder": "sam2/sam2_image_encoder.onnx",
    "mask_decoder": "sam2/sam2_mask_decoder.onnx",
    "memory_attention": "sam2/sam2_memory_attention.onnx",
    "memory_encoder": "sam2/sam2_memory_encoder.onnx",
    "constants": "sam2/sam2_constants.npz",
}
GDINO_FILES = {"model": "groundingdino/groundingdino.onnx", "vocab": "groundingdino/vocab.txt"}


@dataclass(frozen=True)
class TensorSpec:
    """One declared tensor of a graph.

    Attributes:
        ours: the contract's name.
        theirs: the name in the ONNX graph.
        dtype: numpy dtype name ("float32", "int64", "bool").
        shape: one entry per axis: an int (fixed) or a string (dynamic, any size).
    """

    ours: str
    theirs: str
    dtype: str
    shape: Tuple[Dim, ...]


@dataclass(frozen=True)
class GraphSpec:
    """The declared inputs and outputs of one ONNX file, in the contract's names."""

    key: str
    path: Path
    inputs: Tuple[TensorSpec, ...]
    outputs: Tuple[TensorSpec, ...]


@dataclass(frozen=True)
class Preprocess:
    """How frames become the graph's image input.

    Attributes:
        size_hw: (height, width) the graph takes, pixels (traced size).
        resize: "stretch" (aspect not kept: SAM2, whose frames all become 1024x1024) or
            "keep_aspect" (Grounding DINO upstream: the short side becomes ``short_side``
            unless the long side would then pass ``max_size``; a frame whose size that way
            is not the traced one is refused, see :func:`keep_aspect_size`).
        short_side, max_size: the keep-aspect rule's sizes (upstream: 800 and 1333).
        interpolation: "bicubic" (PIL, as SAM2's frame loader) or "bilinear".
        mean, std: per-channel normalisation of RGB values in [0, 1].
        rgb: channel order of the graph input (False means BGR).
    """

    size_hw: Tuple[int, int] = (1024, 1024)
    resize: str = "stretch"
    interpolation: str = "bicubic"
    mean: Tuple[float, float, float] = (0.485, 0.456, 0.406)
    std: Tuple[float, float, float] = (0.229, 0.224, 0.225)
    rgb: bool = True
    short_side: int = 800
    max_size: int = 1333


def keep_aspect_size(height: int, width: int, short_side: int = 800, max_size: int = 1333) -> Tuple[int, int]:
    """(height, width) a frame is resized to by Grounding DINO's own loader (its
    ``RandomResize([800], max_size=1333)``): the short side becomes ``short_side``, or less
    when the long side would pass ``max_size``; the long side is truncated, not rounded."""
    short, long = float(min(height, width)), float(max(height, width))
    size = short_side
    if max_size and long / short * size > max_size:
        size = int(round(max_size * short / long))
    if min(height, width) == size:
        return int(height), int(width)
    if width < height:
        return int(size * height / width), size
    return size, int(size * width / height)


@dataclass(frozen=True)
class Sam2Layout:
    """Layout flags of a SAM2 export (contract § manifest.json)."""

    curr_layout: str = "hw1c"  # "hw1c": curr is [4096,1,256]; "nchw": [1,256,64,64]
    encoder_feat_has_no_mem_embed: bool = False
    decoder_mask_planes: int = 4  # 4 (all tokens) | 3 (multimask only) | 1 (choice baked in)
    decoder_outputs_obj_ptr: bool = True
    ptr_mode: str = "separate"  # "separate" | "concat_memory" | "none"
    memenc_takes_object_score: bool = True


@dataclass(frozen=True)
class Sam2Config:
    """SAM2 host-side constants; defaults are the released video-predictor settings."""

    num_maskmem: int = 7
    max_obj_ptrs: int = 16
    # SAM2.1: pointer position = Linear(sine(signed distance / (min(frames,16)-1)));
    # SAM2.0: zero position.
    add_tpos_enc_to_obj_ptrs: bool = True
    proj_tpos_enc_in_obj_ptrs: bool = True
    use_signed_tpos_enc_to_obj_ptrs: bool = True
    only_obj_ptrs_in_the_past: bool = True
    sigmoid_scale: float = 20.0
    sigmoid_bias: float = -10.0
    stability_delta: float = 0.05
    stability_thresh: float = 0.98
    fill_hole_area: int = 8
    mem_dim: int = 64
    hidden_dim: int = 256
    multimask_output_in_sam: bool = True
    multimask_output_for_tracking: bool = True
    multimask_min_pt_num: int = 0
    multimask_max_pt_num: int = 1
    use_multimask_token_for_obj_ptr: bool = True
    binarize_mask_from_pts: bool = True
    # upstream stores memory features in bfloat16; rounding here keeps parity with it
    memory_bfloat16: bool = True
    image_size: int = 1024


@dataclass(frozen=True)
class GdinoConfig:
    """Grounding DINO host-side constants."""

    num_queries: int = 900
    max_text_len: int = 256
    cls_id: int = 101
    sep_id: int = 102
    special_ids: Tuple[int, ...] = (101, 102, 1012, 1029)  # [CLS] [SEP] . ?
    text_mask_on_host: bool = True


@dataclass(frozen=True)
class Sam2Manifest:
    graphs: Dict[str, GraphSpec]
    constants_path: Path
    layout: Sam2Layout
    preprocess: Preprocess
    config: Sam2Config

    @property
    def has_video(self) -> bool:
        """True when the memory graphs are present (video propagation possible)."""
        return "memory_attention" in self.graphs and "memory_encoder" in self.graphs


@dataclass(frozen=True)
class GdinoManifest:
    graph: GraphSpec
    vocab_path: Path
    preprocess: Preprocess
    config: GdinoConfig


@dataclass(frozen=True)
class Manifest:
    root: Path
    sam2: Optional[Sam2Manifest]
    gdino: Optional[GdinoManifest]


# ----------------------------------------------------------------------------------------
# Contract tables, adjusted by layout flags
# ----------------------------------------------------------------------------------------
def sam2_contract(layout: Sam2Layout) -> Dict[str, Tuple[dict, dict]]:
    """Our (inputs, outputs) tables for each SAM2 graph under ``layout``."""
    dec_out = dict(SAM2_DECODER_OUT)
    planes = layout.decoder_mask_planes
    dec_out["low_res_masks"] = ("float32", [1, planes, 256, 256])
    dec_out["iou_predictions"] = ("float32", [1, planes])
    if layout.decoder_outputs_obj_ptr:
        dec_out["obj_ptr"] = ("float32", [1, planes, 256])
    else:
        dec_out.pop("obj_ptr")
    attn_in = dict(SAM2_MEMATTN_IN)
    if layout.curr_layout == "nchw":
        attn_in["curr"] = ("float32", [1, 256, 64, 64])
        attn_in["curr_pos"] = ("float32", [1, 256, 64, 64])
    if layout.ptr_mode != "separate":
        attn_in.pop("obj_ptr_tokens")
        attn_in.pop("obj_ptr_pos")
    if layout.ptr_mode == "concat_memory":
        attn_in["memory"] = ("float32", ["4096*M+4*P", 1, 64])
        attn_in["memory_pos"] = ("float32", ["4096*M+4*P", 1, 64])
        attn_in["num_obj_ptr_tokens"] = ("int64", [1])
    enc_in = dict(SAM2_MEMENC_IN)
    if not layout.memenc_takes_object_score:
        enc_in.pop("object_score_logits")
    return {
        "image_encoder": (dict(SAM2_ENCODER_IN), dict(SAM2_ENCODER_OUT)),
        "mask_decoder": (dict(SAM2_DECODER_IN), dec_out),
        "memory_attention": (attn_in, dict(SAM2_MEMATTN_OUT)),
        "memory_encoder": (enc_in, dict(SAM2_MEMENC_OUT)),
    }


def gdino_contract() -> Tuple[dict, dict]:
    return dict(GDINO_IN), dict(GDINO_OUT)


# ----------------------------------------------------------------------------------------
# Reading
# ----------------------------------------------------------------------------------------
def _field(obj: dict, key: str, kind, where: str, path: Path, default=None, required=False):
    if key not in obj:
        if required:
            raise ModelError(f"{where}: missing field '{key}'", path)
        return default
    value = obj[key]
    if kind is not None and not isinstance(value, kind):
        names = kind.__name__ if isinstance(kind, type) else "/".join(k.__name__ for k in kind)
        raise ModelError(
            f"{where}.{key}: expected {names}, found {type(value).__name__} ({value!r})", path
        )
    return value


def _dataclass_from(cls, obj: Optional[dict], where: str, path: Path):
    """Build a frozen config dataclass from a dict, rejecting unknown keys and bad types."""
    obj = obj or {}
    if not isinstance(obj, dict):
        raise ModelError(f"{where}: expected an object, found {type(obj).__name__}", path)
    defaults = cls()
    known = {f: getattr(defaults, f) for f in cls.__dataclass_fields__}
    unknown = sorted(set(obj) - set(known))
    if unknown:
        raise ModelError(f"{where}: unknown field(s) {unknown}; known: {sorted(known)}", path)
    kwargs = {}
    for key, value in obj.items():
        want = known[key]
        if isinstance(want, bool):
            ok = isinstance(value, bool)
        elif isinstance(want, int):
            ok = isinstance(value, int) and not isinstance(value, bool)
        elif isinstance(want, float):
            ok = isinstance(value, (int, float)) and not isinstance(value, bool)
            value = float(value) if ok else value
        elif isinstance(want, tuple):
            ok = isinstance(value, list)
            value = tuple(value) if ok else value
        else:
            ok = isinstance(value, type(want))
        if not ok:
            raise ModelError(
                f"{where}.{key}: expected {type(want).__name__}, found "
                f"{type(value).__name__} ({value!r})",
                path,
            )
        kwargs[key] = value
    return cls(**kwargs)


def _preprocess(obj: Optional[dict], default: Preprocess, where: str, path: Path) -> Preprocess:
    obj = dict(obj or {})
    if "size" in obj:  # manifest spells it "size": [h, w]
        obj["size_hw"] = obj.pop("size")
    merged = {**asdict(default), **obj}
    merged = {k: (list(v) if isinstance(v, tuple) else v) for k, v in merged.items()}
    pre = _dataclass_from(Preprocess, merged, where, path)
    if pre.resize not in ("stretch", "keep_aspect"):
        raise ModelError(f"{where}.resize: expected 'stretch' or 'keep_aspect', found {pre.resize!r}", path)
    if pre.short_side < 1 or pre.max_size < 0:
        raise ModelError(f"{where}: short_side must be >= 1 and max_size >= 0", path)
    if pre.interpolation not in ("bicubic", "bilinear"):
        raise ModelError(
            f"{where}.interpolation: expected 'bicubic' or 'bilinear', found "
            f"{pre.interpolation!r}",
            path,
        )
    if len(pre.size_hw) != 2 or len(pre.mean) != 3 or len(pre.std) != 3:
        raise ModelError(f"{where}: size must have 2 entries, mean and std 3 each", path)
    return pre


def _graph_spec(
    key: str,
    model: dict,
    contract: Tuple[dict, dict],
    file_rel: str,
    root: Path,
    where: str,
    mpath: Path,
) -> GraphSpec:
    io = _field(model, "io", dict, where, mpath, default={}) or {}
    io = _field(io, key, dict, f"{where}.io", mpath, default={}) or {}
    dtypes = (_field(model, "dtype", dict, where, mpath, default={}) or {}).get(key, {}) or {}
    shapes = (_field(model, "shape", dict, where, mpath, default={}) or {}).get(key, {}) or {}
    ins, outs = contract
    unknown = sorted(set(io) - set(ins) - set(outs))
    if unknown:
        raise ModelError(
            f"{where}.io.{key}: unknown tensor name(s) {unknown}; the contract's names are "
            f"inputs {sorted(ins)}, outputs {sorted(outs)}",
            mpath,
        )

    def specs(table: dict) -> Tuple[TensorSpec, ...]:
        out = []
        for ours, (dtype, shape) in table.items():
            theirs = io.get(ours, ours)
            dt = dtypes.get(ours, dtype)
            sh = shapes.get(ours, shape)
            if not isinstance(theirs, str) or not isinstance(dt, str) or not isinstance(sh, list):
                raise ModelError(
                    f"{where}: tensor '{ours}' of {key}: io must map to a string, dtype be a "
                    f"string and shape a list; found {theirs!r}, {dt!r}, {sh!r}",
                    mpath,
                )
            out.append(TensorSpec(ours, theirs, dt, tuple(sh)))
        return tuple(out)

    return GraphSpec(key=key, path=root / file_rel, inputs=specs(ins), outputs=specs(outs))


def load_manifest(models_dir: Union[str, os.PathLike]) -> Manifest:
    """Read and validate ``<models_dir>/manifest.json`` (files are checked, graphs are not).

    Raises:
        ModelsNotConfiguredError: the folder or its manifest does not exist.
        ModelError: the manifest is malformed or names a file that is missing.
    """
    if models_dir is None or str(models_dir) == "":
        raise ModelsNotConfiguredError(
            "no model folder is configured: run `cobgs export-onnx sam2|gdino ... --out DIR` "
            "where torch and the checkpoints are, and pass DIR as the models folder"
        )
    root = Path(models_dir)
    mpath = root / MANIFEST_NAME
    if not root.is_dir():
        raise ModelsNotConfiguredError("model folder does not exist", root)
    if not mpath.is_file():
        raise ModelsNotConfiguredError(
            f"no {MANIFEST_NAME} in the model folder (see ONNX contract; "
            "`cobgs export-onnx` writes one)",
            root,
        )
    try:
        data = json.loads(mpath.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ModelError(f"cannot read manifest: {exc}", mpath) from exc
    if not isinstance(data, dict):
        raise ModelError(f"expected a JSON object, found {type(data).__name__}", mpath)
    fmt = data.get("format", FORMAT)
    if fmt != FORMAT:
        raise ModelError(f"format: expected {FORMAT!r}, found {fmt!r}", mpath)
    version = data.get("version", VERSION)
    if version != VERSION:
        raise ModelError(f"version: expected {VERSION}, found {version!r}", mpath)
    unknown = sorted(set(data) - {"format", "version", "sam2", "groundingdino", "note"})
    if unknown:
        raise ModelError(f"unknown top-level field(s) {unknown}", mpath)

    sam2 = _read_sam2(data["sam2"], root, mpath) if "sam2" in data else None
    gdino = _read_gdino(data["groundingdino"], root, mpath) if "groundingdino" in data else None
    if sam2 is None and gdino is None:
        raise ModelsNotConfiguredError("manifest declares neither 'sam2' nor 'groundingdino'",
                                       mpath)
    return Manifest(root=root, sam2=sam2, gdino=gdino)


def _check_file(root: Path, rel: str, where: str, mpath: Path) -> None:
    if not (root / rel).is_file():
        raise ModelError(f"{where}: file '{rel}' does not exist in {root}", mpath)


def _read_sam2(model: dict, root: Path, mpath: Path) -> Sam2Manifest:
    where = "sam2"
    if not isinstance(model, dict):
        raise ModelError(f"{where}: expected an object", mpath)
    files = _field(model, "files", dict, where, mpath, required=True)
    layout = _dataclass_from(Sam2Layout, model.get("layout"), f"{where}.layout", mpath)
    if layout.curr_layout not in ("hw1c", "nchw"):
        raise ModelError(
            f"{where}.layout.curr_layout: expected 'hw1c' or 'nchw', found "
            f"{layout.curr_layout!r}",
            mpath,
        )
    if layout.decoder_mask_planes not in (1, 3, 4):
        raise ModelError(
            f"{where}.layout.decoder_mask_planes: expected 4, 3 or 1, found "
            f"{layout.decoder_mask_planes}",
            mpath,
        )
    if layout.ptr_mode not in ("separate", "concat_memory", "none"):
        raise ModelError(
            f"{where}.layout.ptr_mode: expected 'separate', 'concat_memory' or 'none', "
            f"found {layout.ptr_mode!r}",
            mpath,
        )
    if layout.ptr_mode != "none" and not layout.decoder_outputs_obj_ptr:
        raise ModelError(
            f"{where}.layout: ptr_mode {layout.ptr_mode!r} needs decoder_outputs_obj_ptr=true",
            mpath,
        )
    config = _dataclass_from(Sam2Config, model.get("sam2_config"), f"{where}.sam2_config", mpath)
    pre = _preprocess(model.get("preprocess"), Preprocess(), f"{where}.preprocess", mpath)
    if pre.resize != "stretch":
        raise ModelError(f"{where}.preprocess.resize: SAM2 takes every frame stretched to "
                         f"{config.image_size}x{config.image_size} (its own loader does), found {pre.resize!r}", mpath)
    if tuple(pre.size_hw) != (config.image_size, config.image_size):
        raise ModelError(
            f"{where}.preprocess.size: expected [{config.image_size}, {config.image_size}], "
            f"found {list(pre.size_hw)}",
            mpath,
        )
    contract = sam2_contract(layout)
    graphs = {}
    for key in SAM2_GRAPHS:
        rel = files.get(key)
        if rel is None:
            if key in ("image_encoder", "mask_decoder"):
                raise ModelError(f"{where}.files: missing '{key}'", mpath)
            continue  # image-only export
        _check_file(root, rel, f"{where}.files.{key}", mpath)
        graphs[key] = _graph_spec(key, model, contract[key], rel, root, where, mpath)
    if ("memory_attention" in graphs) != ("memory_encoder" in graphs):
        raise ModelError(
            f"{where}.files: give both memory_attention and memory_encoder, or neither "
            "(image-only export)",
            mpath,
        )
    const_rel = files.get("constants")
    if const_rel is None:
        raise ModelError(f"{where}.files: missing 'constants' (sam2_constants.npz)", mpath)
    _check_file(root, const_rel, f"{where}.files.constants", mpath)
    return Sam2Manifest(graphs, root / const_rel, layout, pre, config)


def _read_gdino(model: dict, root: Path, mpath: Path) -> GdinoManifest:
    where = "groundingdino"
    if not isinstance(model, dict):
        raise ModelError(f"{where}: expected an object", mpath)
    files = _field(model, "files", dict, where, mpath, required=True)
    for key in ("model", "vocab"):
        if key not in files:
            raise ModelError(f"{where}.files: missing '{key}'", mpath)
        _check_file(root, files[key], f"{where}.files.{key}", mpath)
    config = _dataclass_from(GdinoConfig, model.get("gdino"), f"{where}.gdino", mpath)
    if not config.text_mask_on_host:
        raise ModelError(
            f"{where}.gdino.text_mask_on_host: only graphs that take the host-built "
            "position_ids and text_token_mask are supported (found false)", mpath)
    # Without a resize entry (exports written before it existed) the upstream rule holds:
    # frames keep their aspect; a graph traced for another aspect is refused, not stretched.
    pre = _preprocess(
        model.get("preprocess"),
        Preprocess(size_hw=(800, 1200), interpolation="bilinear", resize="keep_aspect"),
        f"{where}.preprocess",
        mpath,
    )
    ins, outs = gdino_contract()
    outs["logits"] = ("float32", [1, config.num_queries, config.max_text_len])
    outs["boxes"] = ("float32", [1, config.num_queries, 4])
    graph = _graph_spec("model", model, (ins, outs), files["model"], root, where, mpath)
    return GdinoManifest(graph, root / files["vocab"], pre, config)


# ----------------------------------------------------------------------------------------
# Writing (used by the export script and by tests that build stand-in graphs)
# ----------------------------------------------------------------------------------------
def sam2_manifest_dict(
    layout: Sam2Layout = Sam2Layout(),
    config: Sam2Config = Sam2Config(),
    video: bool = True,
    io: Optional[Dict[str, Dict[str, str]]] = None,
    files: Optional[Dict[str, str]] = None,
) -> dict:
    """The ``sam2`` entry of a manifest for an export that follows the contract."""
    contract = sam2_contract(layout)
    keys = SAM2_GRAPHS if video else SAM2_GRAPHS[:2]
    fl = {k: v for k, v in SAM2_FILES.items() if k in keys or k == "constants"}
    fl.update(files or {})
    return {
        "files": fl,
        "io": {k: dict((io or {}).get(k, {})) for k in keys},
        "dtype": {k: {n: d for n, (d, _) in {**contract[k][0], **contract[k][1]}.items()}
                  for k in keys},
        "shape": {k: {n: list(s) for n, (_, s) in {**contract[k][0], **contract[k][1]}.items()}
                  for k in keys},
        "layout": asdict(layout),
        "preprocess": _preprocess_dict(Preprocess()),
        "sam2_config": asdict(config),
    }


def gdino_manifest_dict(
    size_hw: Tuple[int, int],
    config: GdinoConfig = GdinoConfig(),
    io: Optional[Dict[str, str]] = None,
    files: Optional[Dict[str, str]] = None,
    resize: str = "keep_aspect",
    short_side: int = 800,
    max_size: int = 1333,
) -> dict:
    """The ``groundingdino`` entry of a manifest for a graph traced at ``size_hw``
    (``resize="stretch"`` only when the user asked to stretch frames of another aspect)."""
    ins, outs = gdino_contract()
    ins["img"] = ("float32", [1, 3, int(size_hw[0]), int(size_hw[1])])
    outs["logits"] = ("float32", [1, config.num_queries, config.max_text_len])
    table = {**ins, **outs}
    cfg = asdict(config)
    cfg["special_ids"] = list(cfg["special_ids"])
    return {
        "files": {**GDINO_FILES, **(files or {})},
        "io": {"model": dict(io or {})},
        "dtype": {"model": {n: d for n, (d, _) in table.items()}},
        "shape": {"model": {n: list(s) for n, (_, s) in table.items()}},
        "preprocess": _preprocess_dict(Preprocess(size_hw=tuple(size_hw), interpolation="bilinear",
                                                  resize=resize, short_side=short_side, max_size=max_size)),
        "gdino": cfg,
    }


def _preprocess_dict(pre: Preprocess) -> dict:
    d = asdict(pre)
    d["size"] = list(d.pop("size_hw"))
    d["mean"] = list(d["mean"])
    d["std"] = list(d["std"])
    return d


def write_manifest(models_dir: Union[str, os.PathLike], entries: dict) -> Path:
    """Merge ``entries`` (``{"sam2": ..., "groundingdino": ...}``) into the folder's manifest.

    An existing manifest keeps the models not in ``entries`` (export SAM2 and Grounding
    DINO one after the other into one folder). Written atomically.
    """
    root = Path(models_dir)
    root.mkdir(parents=True, exist_ok=True)
    mpath = root / MANIFEST_NAME
    data = {"format": FORMAT, "version": VERSION}
    if mpath.is_file():
        try:
            old = json.loads(mpath.read_text())
            if isinstance(old, dict):
                data.update({k: v for k, v in old.items() if k in ("sam2", "groundingdino")})
        except (OSError, json.JSONDecodeError):
            pass  # a broken manifest is replaced
    data.update(entries)
    write_text_atomic(mpath, json.dumps(data, indent=2) + "\n")
    return mpath


def field_names(cls) -> List[str]:
    return list(cls.__dataclass_fields__)


__all__ = [
    "keep_aspect_size", "Dim", "GdinoConfig", "GdinoManifest", "GraphSpec", "Manifest", "ModelsNotConfiguredError",
    "Preprocess", "Sam2Config", "Sam2Layout", "Sam2Manifest", "TensorSpec", "load_manifest",
    "sam2_contract", "gdino_contract", "sam2_manifest_dict", "gdino_manifest_dict",
    "write_manifest",
]
