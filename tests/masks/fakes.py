"""Stand-in SAM2 and Grounding DINO exports that obey the ONNX contract exactly.

No weights can be had here, so these tiny torch modules, exported with torch.onnx at
opset 17, take and return the contract's tensors (names, dtypes, shapes, dynamic axes)
with behaviour the tests control:

* encoder: average-pools the normalised frame; channels 0..2 of every feature map carry
  the pooled colour.
* decoder: with a prompt, the mask is the saturated (coloured) pixels inside the box /
  the positive points' bounding box grown by 160 units; without one, the pixels whose
  colour matches the colour signature that memory attention wrote into channels 3..5 of
  the embedding.
  Planes are logit + (-0.3, -0.2, 0, -0.1) with IoUs (0.5, 0.6, 0.9, 0.7), so the
  multimask choice (token 2) and the single-mask choice (token 0) differ measurably;
  the object score is the largest logit; obj_ptr[k] = (k, present, 0, ...).
* memory encoder: channels 0..2 = mean colour under the mask, channel 3 = present.
* memory attention: the signature of the *last present* memory in the order fed (the
  most recent frame) goes to channels 3..5, presence to channel 6.
* detector: finds saturated pixels only when the caption holds the word "square";
  confidence 0.9 x visible fraction of the full object area; query 1 is a fixed weak
  distractor (0.35); logits are -inf past the caption length.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Dict, Optional

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from cobgs.masks.manifest import (Sam2Config, Sam2Layout, gdino_manifest_dict,
                                  sam2_manifest_dict, write_manifest)

POINT_MARGIN = 160.0  # in the 1024 frame: 10 px across, 7.5 px down a 64x48 frame
SAT_THRESHOLD = 2.0  # normalised max-min channel spread: grey ~0.35, pure red/green ~4.4


class FakeEncoder(nn.Module):
    def forward(self, image):
        c64 = F.avg_pool2d(image, 16)
        feats = torch.cat([c64, torch.zeros(1, 253, 64, 64)], 1)
        pos = feats * 0 + 0.01
        hr0 = torch.cat([F.avg_pool2d(image, 4), torch.zeros(1, 29, 256, 256)], 1)
        hr1 = torch.cat([F.avg_pool2d(image, 8), torch.zeros(1, 61, 128, 128)], 1)
        return feats, pos, hr0, hr1


class FakeEncoderAddsNoMem(FakeEncoder):
    """An export that folds no_mem_embed into its features (some public exports do)."""

    def __init__(self, no_mem_embed: torch.Tensor):
        super().__init__()
        self.register_buffer("nme", no_mem_embed.reshape(1, -1, 1, 1))

    def forward(self, image):
        feats, pos, hr0, hr1 = super().forward(image)
        return feats + self.nme, pos, hr0, hr1


class FakeDecoder(nn.Module):
    def __init__(self, planes: int = 4, with_ptr: bool = True):
        super().__init__()
        self.planes = planes
        self.with_ptr = with_ptr
        grid = (torch.arange(256, dtype=torch.float32) + 0.5) * 4.0
        self.register_buffer("gx", grid.reshape(1, 1, 256))
        self.register_buffer("gy", grid.reshape(1, 256, 1))

    def forward(self, image_embed, hr0, hr1, point_coords, point_labels, mask_input,
                has_mask_input):
        col = hr0[:, 0:3]
        sat = col.amax(1) - col.amin(1)  # [1,256,256]
        x = point_coords[..., 0]
        y = point_coords[..., 1]
        lab = point_labels
        big = 1.0e4
        is_min = (lab == 1) | (lab == 2)
        is_max = (lab == 1) | (lab == 3)
        # positive points claim a margin around them (the square is 12 px)
        margin = (lab == 1).float() * POINT_MARGIN
        x0 = torch.where(is_min, x - margin, torch.full_like(x, big)).amin(-1).reshape(1, 1, 1)
        y0 = torch.where(is_min, y - margin, torch.full_like(y, big)).amin(-1).reshape(1, 1, 1)
        x1 = torch.where(is_max, x + margin, torch.full_like(x, -big)).amax(-1).reshape(1, 1, 1)
        y1 = torch.where(is_max, y + margin, torch.full_like(y, -big)).amax(-1).reshape(1, 1, 1)
        inside = (self.gx >= x0) & (self.gx <= x1) & (self.gy >= y0) & (self.gy <= y1)
        has_prompt = (lab >= 0).any()
        cond = torch.where(inside, 4.0 * (sat - SAT_THRESHOLD), torch.full_like(sat, -8.0))
        sig = image_embed[:, 3:6].mean((2, 3)).reshape(1, 3, 1, 1)
        present = image_embed[:, 6].mean()
        dist = (col - sig).abs().sum(1)
        track = torch.where(present > 0.5, 4.0 * (1.0 - dist), torch.full_like(dist, -8.0))
        logit = torch.where(has_prompt, cond, track)
        logit = logit + 0.0 * (hr1.sum() + mask_input.sum() + has_mask_input.sum())
        offs = torch.tensor([-0.3, -0.2, 0.0, -0.1])
        ious = torch.tensor([[0.5, 0.6, 0.9, 0.7]])
        if self.planes == 3:
            offs, ious = offs[1:], ious[:, 1:]
        elif self.planes == 1:
            offs, ious = offs[2:3], ious[:, 2:3]
        masks = logit.unsqueeze(1) + offs.reshape(1, -1, 1, 1)
        score = logit.amax().reshape(1, 1)
        k = torch.arange(self.planes, dtype=torch.float32).reshape(1, -1, 1)
        flag = (score > 0).float().reshape(1, 1, 1).expand(1, self.planes, 1)
        ptr = torch.cat([k, flag, torch.zeros(1, self.planes, 254)], 2)
        if self.with_ptr:
            return masks, ious + 0.0 * score, ptr, score
        return masks, ious + 0.0 * score, score


class FakeMemoryEncoder(nn.Module):
    def __init__(self, takes_score: bool = True):
        super().__init__()
        self.takes_score = takes_score

    def _run(self, pix_feat, mask_for_mem, score):
        w = F.avg_pool2d((mask_for_mem + 10.0) / 20.0, 16)  # [1,1,64,64]
        total = w.sum()
        sig = (pix_feat[:, 0:3] * w).sum((2, 3)) / (total + 1e-6)
        present = (total > 1.0).float()
        if score is not None:
            present = present * (score.reshape(()) > 0).float()
        feat = torch.cat([sig.reshape(1, 3, 1, 1).expand(1, 3, 64, 64),
                          present.reshape(1, 1, 1, 1).expand(1, 1, 64, 64),
                          torch.zeros(1, 60, 64, 64)], 1)
        return feat, feat * 0 + 0.02

    def forward(self, pix_feat, mask_for_mem, object_score_logits=None):
        return self._run(pix_feat, mask_for_mem, object_score_logits)


class FakeMemoryEncoderNoScore(FakeMemoryEncoder):
    def forward(self, pix_feat, mask_for_mem):
        return self._run(pix_feat, mask_for_mem, None)


class FakeMemoryAttention(nn.Module):
    def _run(self, curr, memory, rest):
        feats = curr.permute(1, 2, 0).reshape(1, 256, 64, 64)
        mem = memory.reshape(-1, 4096, 64)[:, 0, :]  # one token per memory frame
        present = mem[:, 3]
        order = torch.cumsum(torch.ones_like(present), 0)
        sel = present * order
        onehot = (sel == sel.amax()).float().reshape(-1, 1)
        sig = ((mem[:, 0:3] * onehot).sum(0) / onehot.sum()).reshape(1, 3, 1, 1)
        sig = sig.expand(1, 3, 64, 64)
        any_present = present.amax().reshape(1, 1, 1, 1).expand(1, 1, 64, 64)
        out = torch.cat([feats[:, 0:3], sig, any_present, torch.zeros(1, 249, 64, 64)], 1)
        return out + 0.0 * rest

    def forward(self, curr, curr_pos, memory, memory_pos, obj_ptr_tokens, obj_ptr_pos):
        rest = curr_pos.sum() + memory_pos.sum() + obj_ptr_tokens.sum() + obj_ptr_pos.sum()
        return self._run(curr, memory, rest)


class FakeMemoryAttentionNCHW(FakeMemoryAttention):
    """curr / curr_pos as [1, 256, 64, 64] (layout flag curr_layout = "nchw")."""

    def forward(self, curr, curr_pos, memory, memory_pos, obj_ptr_tokens, obj_ptr_pos):
        rest = curr_pos.sum() + memory_pos.sum() + obj_ptr_tokens.sum() + obj_ptr_pos.sum()
        return self._run(curr.flatten(2).permute(2, 0, 1), memory, rest)


class FakeMemoryAttentionConcat(FakeMemoryAttention):
    """Pointers appended to the memory, their count as an input (ptr_mode concat_memory)."""

    def forward(self, curr, curr_pos, memory, memory_pos, num_obj_ptr_tokens):
        spatial = memory[: memory.shape[0] - num_obj_ptr_tokens[0]]
        return self._run(curr, spatial, curr_pos.sum() + memory_pos.sum())


class FakeMemoryAttentionNoPtr(FakeMemoryAttention):
    def forward(self, curr, curr_pos, memory, memory_pos):
        return self._run(curr, memory, curr_pos.sum() + memory_pos.sum())


class FakeDetector(nn.Module):
    """Grounding DINO stand-in traced at a fixed [H, W]."""

    def __init__(self, hw, full_area_px: float, word_id: int, distractor: float = 0.35):
        super().__init__()
        h, w = hw
        self.h, self.w = h, w
        self.full_area = float(full_area_px)
        self.word_id = word_id
        self.distractor_logit = float(np.log(distractor / (1 - distractor)))
        self.register_buffer("gx", ((torch.arange(w, dtype=torch.float32) + 0.5) / w)
                             .reshape(1, 1, w))
        self.register_buffer("gy", ((torch.arange(h, dtype=torch.float32) + 0.5) / h)
                             .reshape(1, h, 1))

    def forward(self, img, input_ids, attention_mask, position_ids, token_type_ids,
                text_token_mask):
        sat = img.amax(1) - img.amin(1)
        m = sat > SAT_THRESHOLD
        count = m.float().sum()
        x0 = torch.where(m, self.gx, torch.full_like(sat, 2.0)).amin() - 0.5 / self.w
        x1 = torch.where(m, self.gx, torch.full_like(sat, -1.0)).amax() + 0.5 / self.w
        y0 = torch.where(m, self.gy, torch.full_like(sat, 2.0)).amin() - 0.5 / self.h
        y1 = torch.where(m, self.gy, torch.full_like(sat, -1.0)).amax() + 0.5 / self.h
        box0 = torch.stack([(x0 + x1) / 2, (y0 + y1) / 2, x1 - x0, y1 - y0]).reshape(1, 1, 4)
        p = torch.clamp(0.9 * count / self.full_area, 1e-4, 0.95)
        has_word = (input_ids == self.word_id).any()
        l0 = torch.where(has_word, torch.log(p / (1 - p)), torch.tensor(-10.0))
        ids = input_ids[0]
        tok_ok = (ids != 101) & (ids != 102) & (ids != 1012) & attention_mask[0]
        n = ids.shape[0]
        row0 = torch.where(tok_ok, l0, torch.tensor(-10.0)).reshape(1, 1, n)
        row1 = torch.where(tok_ok & has_word, torch.tensor(self.distractor_logit),
                           torch.tensor(-10.0)).reshape(1, 1, n)
        rest = torch.full((1, 898, 1), -10.0).expand(1, 898, n)
        logits = torch.cat([row0, row1, rest], 1)
        pad = torch.full((1, 900, 1), float("-inf")).expand(1, 900, 256 - n)
        zero = 0.0 * (position_ids.sum() + token_type_ids.sum() + text_token_mask.sum()).float()
        logits = torch.cat([logits, pad], 2) + zero
        box1 = torch.tensor([[[0.1, 0.1, 0.05, 0.05]]])
        boxes = torch.cat([box0, box1, torch.zeros(1, 898, 4)], 1)
        return logits, boxes


def export(module, args, path: Path, inputs, outputs, dynamic=None) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(module.eval(), tuple(args), str(path), dynamo=False, opset_version=17,
                          input_names=list(inputs), output_names=list(outputs),
                          dynamic_axes=dynamic or {})


def sam2_constants(path: Path, v21: bool = True, seed: int = 0, extra: Optional[dict] = None):
    rng = np.random.default_rng(seed)
    c = {
        "no_mem_embed": np.zeros((1, 1, 256), np.float32),
        "maskmem_tpos_enc": (rng.standard_normal((7, 1, 1, 64)) * 0.02).astype(np.float32),
        "mask_downsample_weight": np.full((1, 1, 4, 4), 1 / 16, np.float32),
        "mask_downsample_bias": np.zeros(1, np.float32),
    }
    if v21:
        c["obj_ptr_tpos_proj_weight"] = (rng.standard_normal((64, 256)) * 0.05).astype(np.float32)
        c["obj_ptr_tpos_proj_bias"] = (rng.standard_normal(64) * 0.05).astype(np.float32)
    c.update(extra or {})
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **c)


ENC_IN = ["image"]
ENC_OUT = ["vision_feats", "vision_pos_embed", "high_res_feats_0", "high_res_feats_1"]
DEC_IN = ["image_embed", "high_res_feats_0", "high_res_feats_1", "point_coords",
          "point_labels", "mask_input", "has_mask_input"]
DEC_OUT = ["low_res_masks", "iou_predictions", "obj_ptr", "object_score_logits"]
ATT_IN = ["curr", "curr_pos", "memory", "memory_pos", "obj_ptr_tokens", "obj_ptr_pos"]
ATT_OUT = ["pix_feat_with_mem"]
MEM_IN = ["pix_feat", "mask_for_mem", "object_score_logits"]
MEM_OUT = ["maskmem_features", "maskmem_pos_enc"]


def build_sam2(
    root: Path,
    v21: bool = True,
    video: bool = True,
    rename: Optional[Dict[str, str]] = None,
    reverse_outputs: bool = False,
    label_dtype=torch.float32,
    fixed_memory: bool = False,
    with_ptr_inputs: bool = True,
    memenc_score: bool = True,
    planes: int = 4,
    write: bool = True,
    curr_nchw: bool = False,
    concat_ptr: bool = False,
    encoder_adds_no_mem_embed: bool = False,
) -> Path:
    """Write ``root/sam2/*`` and the manifest's ``sam2`` entry; returns ``root``.

    ``rename`` maps our tensor names to the export's (applied to every graph);
    the manifest's ``io`` then maps them back.
    """
    rename = rename or {}
    r = lambda names: [rename.get(n, n) for n in names]  # noqa: E731
    sam = root / "sam2"
    order = (lambda x: x[::-1]) if reverse_outputs else (lambda x: x)
    enc_args = (torch.zeros(1, 3, 1024, 1024),)

    class Reorder(nn.Module):
        def __init__(self, inner):
            super().__init__()
            self.inner = inner

        def forward(self, *a):
            out = self.inner(*a)
            return out if torch.is_tensor(out) else tuple(order(list(out)))

    nme = torch.zeros(256)
    nme[0] = 0.5  # visible in the colour channels if the host forgot to subtract it
    encoder = FakeEncoderAddsNoMem(nme) if encoder_adds_no_mem_embed else FakeEncoder()
    export(Reorder(encoder), enc_args, sam / "sam2_image_encoder.onnx", r(ENC_IN),
           order(r(ENC_OUT)))
    dec_args = (torch.zeros(1, 256, 64, 64), torch.zeros(1, 32, 256, 256),
                torch.zeros(1, 64, 128, 128), torch.zeros(1, 2, 2),
                torch.zeros(1, 2, dtype=label_dtype), torch.zeros(1, 1, 256, 256),
                torch.zeros(1))
    dec_out = DEC_OUT
    export(Reorder(FakeDecoder(planes=planes)), dec_args, sam / "sam2_mask_decoder.onnx",
           r(DEC_IN), order(r(dec_out)),
           {rename.get("point_coords", "point_coords"): {1: "N"},
            rename.get("point_labels", "point_labels"): {1: "N"}})
    layout = Sam2Layout(decoder_mask_planes=planes,
                        ptr_mode=("concat_memory" if concat_ptr else
                                  "separate" if with_ptr_inputs else "none"),
                        memenc_takes_object_score=memenc_score,
                        curr_layout="nchw" if curr_nchw else "hw1c",
                        encoder_feat_has_no_mem_embed=encoder_adds_no_mem_embed)
    if video:
        if concat_ptr:
            att_args = (torch.zeros(4096, 1, 256), torch.zeros(4096, 1, 256),
                        torch.zeros(4096 * 2 + 8, 1, 64), torch.zeros(4096 * 2 + 8, 1, 64),
                        torch.tensor([8], dtype=torch.int64))
            att_in = ATT_IN[:4] + ["num_obj_ptr_tokens"]
            att_mod = FakeMemoryAttentionConcat()
        elif curr_nchw:
            att_args = (torch.zeros(1, 256, 64, 64), torch.zeros(1, 256, 64, 64),
                        torch.zeros(4096 * 2, 1, 64), torch.zeros(4096 * 2, 1, 64),
                        torch.zeros(8, 1, 64), torch.zeros(8, 1, 64))
            att_in = ATT_IN
            att_mod = FakeMemoryAttentionNCHW()
        elif with_ptr_inputs:
            att_args = (torch.zeros(4096, 1, 256), torch.zeros(4096, 1, 256),
                        torch.zeros(4096 * 2, 1, 64), torch.zeros(4096 * 2, 1, 64),
                        torch.zeros(8, 1, 64), torch.zeros(8, 1, 64))
            att_in = ATT_IN
            att_mod = FakeMemoryAttention()
        else:
            att_args = (torch.zeros(4096, 1, 256), torch.zeros(4096, 1, 256),
                        torch.zeros(4096 * 2, 1, 64), torch.zeros(4096 * 2, 1, 64))
            att_in = ATT_IN[:4]
            att_mod = FakeMemoryAttentionNoPtr()
        dyn = {} if fixed_memory else {
            rename.get(n, n): {0: n + "_len"} for n in att_in[2:6] if n != "num_obj_ptr_tokens"}
        export(Reorder(att_mod), att_args, sam / "sam2_memory_attention.onnx", r(att_in),
               r(ATT_OUT), dyn)
        if memenc_score:
            mem_args = (torch.zeros(1, 256, 64, 64), torch.zeros(1, 1, 1024, 1024),
                        torch.ones(1, 1))
            export(Reorder(FakeMemoryEncoder()), mem_args, sam / "sam2_memory_encoder.onnx",
                   r(MEM_IN), order(r(MEM_OUT)))
        else:
            mem_args = (torch.zeros(1, 256, 64, 64), torch.zeros(1, 1, 1024, 1024))
            export(Reorder(FakeMemoryEncoderNoScore()), mem_args,
                   sam / "sam2_memory_encoder.onnx", r(MEM_IN[:2]), order(r(MEM_OUT)))
    sam2_constants(sam / "sam2_constants.npz", v21=v21,
                   extra={"no_mem_embed": nme.numpy().reshape(1, 1, 256)}
                   if encoder_adds_no_mem_embed else None)
    if write:
        cfg = Sam2Config() if v21 else Sam2Config(add_tpos_enc_to_obj_ptrs=False,
                                                  proj_tpos_enc_in_obj_ptrs=False,
                                                  use_signed_tpos_enc_to_obj_ptrs=False)
        graphs = ["image_encoder", "mask_decoder"] + (
            ["memory_attention", "memory_encoder"] if video else [])
        io = {g: {k: v for k, v in rename.items()} for g in graphs}
        entry = sam2_manifest_dict(layout, cfg, video=video, io=_valid_io(io, layout, video))
        write_manifest(root, {"sam2": entry})
    return root


def _valid_io(io, layout, video):
    from cobgs.masks.manifest import sam2_contract

    c = sam2_contract(layout)
    return {g: {k: v for k, v in m.items() if k in c[g][0] or k in c[g][1]} for g, m in io.items()}


# -------------------------------------------------------------------------- detector
WORDS = {"square": 2000, "red": 2001, "green": 2002, "apple": 2003}


def write_vocab(path: Path, size: int = 2100) -> None:
    """A BERT-style vocab whose special ids are bert-base-uncased's (101, 102, 1012, 1029)."""
    lines = [f"[unused{i}]" for i in range(size)]
    lines[0] = "[PAD]"
    lines[100] = "[UNK]"
    lines[101] = "[CLS]"
    lines[102] = "[SEP]"
    lines[103] = "[MASK]"
    lines[1012] = "."
    lines[1029] = "?"
    lines[1010] = ","
    for word, i in WORDS.items():
        lines[i] = word
    lines[2010] = "##s"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")


def build_gdino(root: Path, hw=(48, 64), full_area_px: float = 144.0, rename=None,
                manifest_hw=None, write: bool = True, mask_dtype=torch.bool) -> Path:
    rename = rename or {}
    r = lambda names: [rename.get(n, n) for n in names]  # noqa: E731
    g = root / "groundingdino"
    names_in = ["img", "input_ids", "attention_mask", "position_ids", "token_type_ids",
                "text_token_mask"]
    args = (torch.zeros(1, 3, *hw), torch.tensor([[101, 2000, 1012, 102]]),
            torch.ones(1, 4, dtype=mask_dtype), torch.zeros(1, 4, dtype=torch.int64),
            torch.zeros(1, 4, dtype=torch.int64), torch.ones(1, 4, 4, dtype=torch.bool))
    dyn = {rename.get(n, n): {1: "L"} for n in names_in[1:]}
    dyn[rename.get("text_token_mask", "text_token_mask")] = {1: "L", 2: "L2"}
    det = FakeDetector(hw, full_area_px, WORDS["square"])
    if mask_dtype is not torch.bool:
        class Cast(nn.Module):
            def __init__(self, inner):
                super().__init__()
                self.inner = inner

            def forward(self, img, ids, am, pos, tt, tm):
                return self.inner(img, ids, am.bool(), pos, tt, tm)
        det = Cast(det)
    export(det, args, g / "groundingdino.onnx", r(names_in), r(["logits", "boxes"]), dyn)
    write_vocab(g / "vocab.txt")
    if write:
        mhw = manifest_hw or hw  # frames of the traced size keep it under the keep-aspect rule
        entry = gdino_manifest_dict(mhw, io={k: v for k, v in rename.items()}, short_side=min(mhw))
        write_manifest(root, {"groundingdino": entry})
    return root


def edit_manifest(root: Path, fn) -> None:
    path = root / "manifest.json"
    data = json.loads(path.read_text())
    fn(data)
    path.write_text(json.dumps(data))
