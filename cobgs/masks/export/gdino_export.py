"""``cobgs export-onnx gdino``: a Grounding DINO checkpoint -> one graph + ``vocab.txt``.

Run where ``torch``, the ``groundingdino`` package (IDEA-Research/GroundingDINO) and its
BERT tokenizer files are available::

    cobgs export-onnx gdino --config GroundingDINO_SwinB_cfg.py \\
        --checkpoint groundingdino_swinb_cogcoor.pth --out models/ --for-frame 756 1008

The graph takes the caption already tokenised (the host does it with the ``tokenizers``
package on the written ``vocab.txt``) and is traced at one fixed image size. Export on
CPU: the multi-scale deformable attention then takes its pure-PyTorch path (grid
sampling), which ONNX can express, instead of the CUDA kernel.
"""

from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path
from typing import List, Optional, Sequence, Tuple

import numpy as np

from cobgs.masks.manifest import GDINO_FILES, GdinoConfig, gdino_manifest_dict, write_manifest
from cobgs.masks.export.common import ExportError, Parity, export_graph, remove_partial, require, verify_graph

log = logging.getLogger("cobgs.masks.export")

GDINO_HINT = ("Install PyTorch and the Grounding DINO code on the machine that holds the checkpoint: "
              "`pip install groundingdino-py==0.4.0 'transformers>=4.40,<5' pycocotools defusedxml "
              "pyDeprecate addict yapf timm supervision` (upstream's imports pull in the last ones; "
              "transformers 5 removed BertModel.get_extended_attention_mask, which it calls; 4.57.6 is "
              "known good), or IDEA-Research/GroundingDINO from source. Its text encoder is "
              "bert-base-uncased: with no model hub reachable, pass a local copy with --bert DIR.")
TRANSFORMERS_MAX_MAJOR = 4  # transformers 5 dropped an API upstream's BERT wrapper calls
INPUTS = ["img", "input_ids", "attention_mask", "position_ids", "token_type_ids",
          "text_token_mask"]
OUTPUTS = ["logits", "boxes"]


def _wrapper_class():
    import torch
    from torch import nn

    misc = require("groundingdino.util.misc", "Grounding DINO", GDINO_HINT)

    class GroundingDinoGraph(nn.Module):
        """Tokenised caption + image -> (logits [1,900,256], boxes [1,900,4]).

        Follows ``GroundingDINO.forward`` with the text tensors as inputs instead of a
        caption string (the module structure used: ``bert``, ``feat_map``, ``backbone``,
        ``input_proj``, ``transformer``, ``bbox_embed``, ``class_embed``,
        ``num_feature_levels``, ``sub_sentence_present``).
        """

        def __init__(self, model):
            super().__init__()
            self.m = model

        def forward(self, img, input_ids, attention_mask, position_ids, token_type_ids,
                    text_token_mask):
            m = self.m
            if m.sub_sentence_present:
                bert = m.bert(input_ids=input_ids, attention_mask=text_token_mask,
                              token_type_ids=token_type_ids, position_ids=position_ids)
            else:
                bert = m.bert(input_ids=input_ids, attention_mask=attention_mask,
                              token_type_ids=token_type_ids)
            text = {
                "encoded_text": m.feat_map(bert["last_hidden_state"]),
                "text_token_mask": attention_mask,
                "position_ids": position_ids,
                "text_self_attention_masks": text_token_mask,
            }
            no_pad = torch.zeros(img.shape[0], img.shape[2], img.shape[3], dtype=torch.bool)
            samples = misc.NestedTensor(img, no_pad)
            features, poss = m.backbone(samples)
            srcs, masks = [], []
            for level, feat in enumerate(features):
                src, mask = feat.decompose()
                srcs.append(m.input_proj[level](src))
                masks.append(mask)
            for level in range(len(srcs), m.num_feature_levels):
                src = m.input_proj[level](features[-1].tensors if level == len(features)
                                          else srcs[-1])
                mask = torch.nn.functional.interpolate(no_pad[None].float(),
                                                       size=src.shape[-2:]).to(torch.bool)[0]
                poss.append(m.backbone[1](misc.NestedTensor(src, mask)).to(src.dtype))
                srcs.append(src)
                masks.append(mask)
            hs, reference, _, _, _ = m.transformer(srcs, masks, None, poss, None, None, text)
            last = len(hs) - 1
            delta = m.bbox_embed[last](hs[last])
            boxes = (delta + misc.inverse_sigmoid(reference[last])).sigmoid()
            logits = m.class_embed[last](hs[last], text)
            return logits, boxes

    return GroundingDinoGraph


def _disable_checkpointing(model) -> None:
    """Gradient checkpointing (on in the released configs) cannot be traced; it only
    saves training memory, so switching it off leaves inference unchanged."""
    for m in model.modules():
        for attr in ("use_checkpoint", "use_transformer_ckpt"):
            if isinstance(getattr(m, attr, None), bool):
                setattr(m, attr, False)


def check_transformers() -> None:
    """Refuse a transformers release upstream's code cannot run on, saying which works."""
    tf = require("transformers", "Grounding DINO", GDINO_HINT)
    major = int(str(tf.__version__).split(".")[0])
    if major > TRANSFORMERS_MAX_MAJOR:
        raise ExportError(f"transformers {tf.__version__} is installed, but Grounding DINO's BERT wrapper "
                          "calls BertModel.get_extended_attention_mask, which transformers 5 removed: "
                          "`pip install 'transformers>=4.40,<5'` (4.57.6 known good)")


def load_gdino(config: str, checkpoint: str, bert: Optional[str] = None):
    """Build Grounding DINO from its config and checkpoint on the CPU; ``bert``: a local
    folder holding bert-base-uncased (config.json, vocab.txt, weights) to use instead of
    the config's hub name."""
    import torch

    require("torch", "Grounding DINO", GDINO_HINT)
    check_transformers()
    models = require("groundingdino.models", "Grounding DINO", GDINO_HINT)
    slconfig = require("groundingdino.util.slconfig", "Grounding DINO", GDINO_HINT)
    for p in (config, checkpoint) + ((bert,) if bert else ()):
        if not Path(p).exists():
            raise ExportError(f"not found: {p}")
    try:
        args = slconfig.SLConfig.fromfile(config)
        args.device = "cpu"
        if bert:
            args.text_encoder_type = os.fspath(Path(bert).resolve())
        model = models.build_model(args)
        state = torch.load(checkpoint, map_location="cpu", weights_only=False)
        state = state.get("model", state)
        model.load_state_dict({k.removeprefix("module."): v for k, v in state.items()}, strict=False)
        return model.eval()
    except Exception as exc:  # the loader raises many types
        raise ExportError(f"cannot load Grounding DINO from {config} / {checkpoint}"
                          + (f" with the BERT folder {bert}" if bert else "") + f": {exc}"
                          + ("" if bert else " (no model hub reachable? pass --bert DIR)")) from exc


def export_gdino(
    out_dir: os.PathLike,
    size_hw: Tuple[int, int] = (800, 1200),
    config: Optional[str] = None,
    checkpoint: Optional[str] = None,
    caption: str = "a cat . a remote control .",
    image: Optional[str] = None,
    verify: bool = True,
    model=None,
    graph_module=None,
    vocab_path: Optional[os.PathLike] = None,
    num_queries: int = 900,
    max_text_len: int = 256,
    resize: str = "keep_aspect",
    short_side: int = 800,
    max_size: int = 1333,
    bert: Optional[str] = None,
) -> List[Parity]:
    """Export, verify and register Grounding DINO in ``out_dir`` (manifest merged).

    Args:
        size_hw: the fixed (height, width) the graph is traced at. Upstream keeps each
            frame's aspect (short side ``short_side``, long side at most ``max_size``), so
            trace at the size the frames get that way (``--for-frame H W`` computes it:
            1008x756 LLFF frames -> 800x1066); the host refuses frames of another aspect.
        resize: "keep_aspect" (upstream) or "stretch" (any frame is stretched to
            ``size_hw``: detections differ from upstream's; only when asked for).
        caption: the caption used for tracing and verification (the caption length
            stays a dynamic axis).
        model: an already-loaded ``GroundingDINO`` (skips loading).
        graph_module: a module with the contract's signature to export instead of the
            wrapper around ``model`` (used to test this machinery without the weights).
        vocab_path: the BERT ``vocab.txt`` (default: saved from the model's tokenizer).
        bert: a local bert-base-uncased folder for the text encoder (no model hub needed).

    Returns:
        the max differences found between onnxruntime and PyTorch.
    """
    import torch

    from cobgs.masks.gdino import Tokenizer
    from cobgs.masks.images import load_rgb, to_model_input
    from cobgs.masks.manifest import Preprocess

    cfg = GdinoConfig(num_queries=num_queries, max_text_len=max_text_len)
    out = Path(out_dir)
    gdir = out / "groundingdino"
    gdir.mkdir(parents=True, exist_ok=True)
    graph_path = out / GDINO_FILES["model"]
    vocab_out = out / GDINO_FILES["vocab"]
    if graph_module is None:
        if model is None:
            if config is None or checkpoint is None:
                raise ExportError("exporting Grounding DINO needs --config and --checkpoint")
            model = load_gdino(config, checkpoint, bert)
        _disable_checkpointing(model)
        graph_module = _wrapper_class()(model).eval()
        if vocab_path is None:
            tok = getattr(model, "tokenizer", None)
            if tok is None or not hasattr(tok, "save_vocabulary"):
                raise ExportError("the model has no BERT tokenizer to take vocab.txt from; "
                                  "pass --vocab")
            saved = tok.save_vocabulary(str(gdir))
            vocab_path = Path(saved[0])
    if vocab_path is None or not Path(vocab_path).is_file():
        raise ExportError(f"vocab.txt not found: {vocab_path}")
    if Path(vocab_path).resolve() != vocab_out.resolve():
        shutil.copyfile(vocab_path, vocab_out)

    pre = Preprocess(size_hw=tuple(size_hw), interpolation="bilinear")
    if image is None:
        rng = np.random.default_rng(0)
        rgb = rng.integers(0, 256, (size_hw[0], size_hw[1], 3), dtype=np.uint8)
    else:
        rgb = load_rgb(image)
    text = Tokenizer(vocab_out, cfg.max_text_len, cfg.special_ids)(caption)
    feeds = {"img": to_model_input(rgb, pre), "input_ids": text.input_ids,
             "attention_mask": text.attention_mask, "position_ids": text.position_ids,
             "token_type_ids": text.token_type_ids, "text_token_mask": text.text_token_mask}
    dyn = {n: {1: "num_tokens"} for n in INPUTS[1:]}
    dyn["text_token_mask"] = {1: "num_tokens", 2: "num_tokens"}
    report: List[Parity] = []
    try:
        export_graph(graph_module, tuple(torch.from_numpy(v) for v in feeds.values()),
                     graph_path, INPUTS, OUTPUTS, dyn)
        if verify:
            # 1e-2 on a logit moves a probability near the 0.3-0.45 thresholds by < 0.003
            # (float drift through 6 fusion/decoder layers reaches a few 1e-3); up to 1%
            # of the 900 queries may differ where the encoder's top-k proposal selection
            # breaks a near-tie differently
            check = dict(atol=1e-2, rtol=1e-3, rows_axis=1, max_bad_rows=0.01)
            report = verify_graph(graph_path, graph_module, feeds, OUTPUTS, **check)
            # another caption length than the traced one
            other = Tokenizer(vocab_out, cfg.max_text_len, cfg.special_ids)(
                caption + " " + caption)
            feeds2 = dict(feeds, input_ids=other.input_ids, attention_mask=other.attention_mask,
                          position_ids=other.position_ids, token_type_ids=other.token_type_ids,
                          text_token_mask=other.text_token_mask)
            report += verify_graph(graph_path, graph_module, feeds2, OUTPUTS, **check)
    except BaseException:
        remove_partial([graph_path])
        raise
    entry = gdino_manifest_dict(tuple(size_hw), cfg, resize=resize, short_side=short_side, max_size=max_size)
    entry["note"] = (f"exported by cobgs from {checkpoint or 'a stand-in module'} "
                     f"at {size_hw[0]}x{size_hw[1]}")
    write_manifest(out, {"groundingdino": entry})
    return report


def parse_size(values: Sequence[int]) -> Tuple[int, int]:
    if len(values) != 2 or any(int(v) <= 0 for v in values):
        raise ExportError(f"--size takes HEIGHT WIDTH (positive), got {list(values)}")
    return int(values[0]), int(values[1])
