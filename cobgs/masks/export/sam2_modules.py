"""Export-friendly wrappers around a ``sam2`` ``SAM2Base`` model's submodules.

Each wrapper takes and returns exactly the contract's tensors. They reuse the model's own
layers and weights; only two pieces are re-expressed for ONNX: the prompt-point
embedding (pure ``torch.where`` arithmetic) and the memory attention's rotary encoding,
which upstream computes with complex numbers that ONNX cannot represent (here: the same
rotation with real cos/sin).

The module structure used (public in the ``sam2`` package): ``model.image_encoder``,
``model.sam_mask_decoder`` (``conv_s0``, ``conv_s1``, ``predict_masks``),
``model.sam_prompt_encoder`` (``pe_layer``, ``point_embeddings``, ``not_a_point_embed``,
``no_mask_embed``, ``mask_downscaling``, ``get_dense_pe``), ``model.obj_ptr_proj``,
``model.no_obj_ptr``, ``model.memory_attention`` (``layers`` of self/cross
``RoPEAttention``, ``norm``), ``model.memory_encoder`` and ``model.no_obj_embed_spatial``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class ImageEncoder(nn.Module):
    """image [1,3,1024,1024] -> raw top-level features, their position, high-res maps."""

    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, image):
        out = self.model.forward_image(image)  # applies conv_s0 / conv_s1 to levels 0, 1
        fpn, pos = out["backbone_fpn"], out["vision_pos_enc"]
        return fpn[-1], pos[-1], fpn[0], fpn[1]


class MaskDecoder(nn.Module):
    """Prompt encoder + mask decoder (all 4 tokens) + object-pointer projection.

    The pointer already carries SAM2's no-object handling (``fixed_no_obj_ptr`` /
    ``no_obj_ptr``), which needs weights the host does not have; the masks do not (the
    host sets them to -1024 where the object score is <= 0).
    """

    def __init__(self, model):
        super().__init__()
        self.model = model
        pe = model.sam_prompt_encoder
        self.image_size = float(model.image_size)
        self.register_buffer("dense_pe", pe.get_dense_pe().detach().clone())

    def _embed_points(self, coords, labels):
        pe = self.model.sam_prompt_encoder
        # SAM2 pads the prompt with one "not a point" when no box is given
        coords = torch.cat([coords + 0.5, torch.zeros_like(coords[:, :1])], 1)
        labels = torch.cat([labels, -torch.ones_like(labels[:, :1])], 1)
        emb = pe.pe_layer._pe_encoding(coords / self.image_size)
        lab = labels.unsqueeze(-1)
        emb = torch.where(lab == -1, torch.zeros_like(emb) + pe.not_a_point_embed.weight, emb)
        for i in range(4):
            emb = torch.where(lab == i, emb + pe.point_embeddings[i].weight, emb)
        return emb

    def forward(self, image_embed, high_res_feats_0, high_res_feats_1, point_coords,
                point_labels, mask_input, has_mask_input):
        m = self.model
        pe = m.sam_prompt_encoder
        sparse = self._embed_points(point_coords, point_labels)
        no_mask = pe.no_mask_embed.weight.reshape(1, -1, 1, 1).expand(1, -1, 64, 64)
        has = has_mask_input.reshape(1, 1, 1, 1)
        dense = has * pe.mask_downscaling(mask_input) + (1 - has) * no_mask
        masks, ious, tokens, score = m.sam_mask_decoder.predict_masks(
            image_embeddings=image_embed, image_pe=self.dense_pe,
            sparse_prompt_embeddings=sparse, dense_prompt_embeddings=dense,
            repeat_image=False, high_res_features=[high_res_feats_0, high_res_feats_1],
        )
        ptr = m.obj_ptr_proj(tokens)  # [1, 4, 256]
        if m.pred_obj_scores:
            lam = score.sigmoid() if m.soft_no_obj_ptr else (score > 0).float()
            lam = lam.unsqueeze(-1)  # [1, 1, 1]
            if m.fixed_no_obj_ptr:
                ptr = lam * ptr
            ptr = ptr + (1 - lam) * m.no_obj_ptr
        return masks, ious, ptr, score


def _axial_angles(dim: int, end_x: int, end_y: int, theta: float) -> torch.Tensor:
    """Rotation angles [end_x*end_y, dim/2] of SAM2's axial RoPE (x half, then y half)."""
    freqs = 1.0 / (theta ** (torch.arange(0, dim, 4)[: dim // 4].float() / dim))
    t = torch.arange(end_x * end_y, dtype=torch.float32)
    tx, ty = t % end_x, torch.div(t, end_x, rounding_mode="floor")
    return torch.cat([torch.outer(tx, freqs), torch.outer(ty, freqs)], -1)


def _rotate(x, cos, sin):
    """Rotate consecutive channel pairs of x [..., N, D] by angles given as cos/sin [N, D/2]."""
    pairs = x.reshape(*x.shape[:-1], -1, 2)
    a, b = pairs[..., 0], pairs[..., 1]
    return torch.stack([a * cos - b * sin, a * sin + b * cos], -1).flatten(-2)


class _RopeAttention(nn.Module):
    """A ``RoPEAttention``'s projections with real-valued rotary encoding."""

    def __init__(self, attn, side: int):
        super().__init__()
        self.attn = attn
        head_dim = attn.internal_dim // attn.num_heads
        # upstream keeps theta in its partial(compute_axial_cis, ...); the token grid is the
        # one memory attention runs on (64 x 64 at 1024 input). Its precomputed table may be
        # for another grid (Grounded-SAM-2's configs say 32 x 32 and upstream recomputes it
        # at the first call), so the grid comes from the model, not from the table.
        theta = getattr(attn.compute_cis, "keywords", {}).get("theta", 10000.0)
        tokens_hw = (side, side)
        ang = _axial_angles(head_dim, tokens_hw[0], tokens_hw[1], theta)
        self.register_buffer("cos", ang.cos())
        self.register_buffer("sin", ang.sin())
        self.n = tokens_hw[0] * tokens_hw[1]

    def _heads(self, x):
        b, n, c = x.shape
        h = self.attn.num_heads
        return x.reshape(b, n, h, c // h).transpose(1, 2)

    def forward(self, q, k_rope, v, k_plain=None, v_plain=None):
        a = self.attn
        q = _rotate(self._heads(a.q_proj(q)), self.cos, self.sin)
        k = self._heads(a.k_proj(k_rope))
        b, h, n, d = k.shape
        # memories repeat the 64x64 rotation per frame: broadcast instead of tiling
        k = _rotate(k.reshape(b, h, -1, self.n, d), self.cos, self.sin).reshape(b, h, -1, d)
        v = self._heads(a.v_proj(v))
        if k_plain is not None:  # object-pointer tokens: no rotary encoding
            k = torch.cat([k, self._heads(a.k_proj(k_plain))], 2)
            v = torch.cat([v, self._heads(a.v_proj(v_plain))], 2)
        out = F.scaled_dot_product_attention(q, k, v)
        b, h, n, d = out.shape
        return a.out_proj(out.transpose(1, 2).reshape(b, n, h * d))


class MemoryAttention(nn.Module):
    """curr/curr_pos [4096,1,256] + memories [4096M,1,64] + pointer tokens [4P,1,64]
    -> pix_feat_with_mem [1,256,64,64]."""

    def __init__(self, model):
        super().__init__()
        self.ma = model.memory_attention
        side = int(model.image_size) // int(getattr(model, "backbone_stride", 16))
        self.self_attn = nn.ModuleList(_RopeAttention(layer.self_attn, side)
                                       for layer in self.ma.layers)
        self.cross_attn = nn.ModuleList(_RopeAttention(layer.cross_attn_image, side)
                                        for layer in self.ma.layers)

    def forward(self, curr, curr_pos, memory, memory_pos, obj_ptr_tokens, obj_ptr_pos):
        ma = self.ma
        out = curr + 0.1 * curr_pos if ma.pos_enc_at_input else curr
        # batch first: [1, tokens, C]
        out, qpos = out.transpose(0, 1), curr_pos.transpose(0, 1)
        mem, mpos = memory.transpose(0, 1), memory_pos.transpose(0, 1)
        ptr, ppos = obj_ptr_tokens.transpose(0, 1), obj_ptr_pos.transpose(0, 1)
        for layer, sa, ca in zip(ma.layers, self.self_attn, self.cross_attn):
            t2 = layer.norm1(out)
            qk = t2 + qpos if layer.pos_enc_at_attn else t2
            out = out + sa(qk, qk, t2)
            t2 = layer.norm2(out)
            q = t2 + qpos if layer.pos_enc_at_cross_attn_queries else t2
            keys = layer.pos_enc_at_cross_attn_keys
            out = out + ca(q, mem + mpos if keys else mem, mem,
                           ptr + ppos if keys else ptr, ptr)
            t2 = layer.norm3(out)
            out = out + layer.linear2(layer.activation(layer.linear1(t2)))
        out = ma.norm(out)  # [1, 4096, 256]
        return out.transpose(1, 2).reshape(1, -1, 64, 64)


class MemoryEncoder(nn.Module):
    """raw features + host-prepared mask (+ object score) -> memory features and position."""

    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, pix_feat, mask_for_mem, object_score_logits):
        m = self.model
        out = m.memory_encoder(pix_feat, mask_for_mem, skip_mask_sigmoid=True)
        feats, pos = out["vision_features"], out["vision_pos_enc"][-1]
        if m.no_obj_embed_spatial is not None:  # SAM2.1 marks frames without the object
            absent = (object_score_logits <= 0).float().reshape(1, 1, 1, 1)
            feats = feats + absent * m.no_obj_embed_spatial.reshape(1, -1, 1, 1)
        else:
            feats = feats + 0.0 * object_score_logits.reshape(1, 1, 1, 1)
        return feats, pos
