"""``cobgs export-onnx sam2``: a ``sam2`` checkpoint -> the contract's 4 graphs + constants.

Run where ``torch`` and Meta's ``sam2`` package are installed::

    cobgs export-onnx sam2 --config configs/sam2.1/sam2.1_hiera_l.yaml \\
        --checkpoint sam2.1_hiera_large.pt --out models/

Every graph is checked against the PyTorch module on one image (``--image``, or a
synthetic one) before the manifest is written; a failed check removes nothing the user
had but leaves no manifest entry pointing at unverified graphs.
"""

from __future__ import annotations

import logging
import os
from dataclasses import asdict
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np

from cobgs.masks.manifest import SAM2_FILES, Sam2Config, Sam2Layout, sam2_manifest_dict, write_manifest
from cobgs.masks.export.common import ExportError, Parity, export_graph, remove_partial, require, verify_graph

log = logging.getLogger("cobgs.masks.export")

SAM2_HINT = ("Install PyTorch and Meta's SAM 2 code from its repository on the machine that holds the "
             "checkpoint: `pip install 'git+https://github.com/facebookresearch/sam2.git@2b90b9f'` "
             "(sam2 1.1.0; the PyPI project named 'sam2' is not Meta's upload). For the predictor the "
             "COB-GS authors ran, put IDEA-Research/Grounded-SAM-2's checkout first on PYTHONPATH "
             "instead (its own sam2 copy). Known good: torch 2.5-2.14, hydra-core 1.3, iopath 0.1.10.")


def build_sam2_model(config: str, checkpoint: Optional[str], device: str = "cpu"):
    """Instantiate a ``SAM2Base`` from a hydra config name and an optional checkpoint."""
    require("torch", "SAM2", SAM2_HINT)
    build = require("sam2.build_sam", "SAM2", SAM2_HINT)
    if checkpoint is not None and not Path(checkpoint).is_file():
        raise ExportError(f"checkpoint not found: {checkpoint}")
    try:
        model = build.build_sam2(config, checkpoint, device=device, mode="eval",
                                 apply_postprocessing=False)
    except Exception as exc:  # hydra / torch.load raise many types
        raise ExportError(f"cannot build SAM2 from config '{config}' and checkpoint "
                          f"'{checkpoint}': {exc}") from exc
    return model.eval()


def sam2_host_config(model) -> Sam2Config:
    """The host-side constants of a ``SAM2Base`` (what the manifest's sam2_config holds)."""
    dec = model.sam_mask_decoder
    return Sam2Config(
        num_maskmem=int(model.num_maskmem),
        max_obj_ptrs=int(model.max_obj_ptrs_in_encoder),
        add_tpos_enc_to_obj_ptrs=bool(model.add_tpos_enc_to_obj_ptrs),
        proj_tpos_enc_in_obj_ptrs=bool(model.proj_tpos_enc_in_obj_ptrs),
        use_signed_tpos_enc_to_obj_ptrs=bool(model.use_signed_tpos_enc_to_obj_ptrs),
        only_obj_ptrs_in_the_past=bool(model.only_obj_ptrs_in_the_past_for_eval),
        sigmoid_scale=float(model.sigmoid_scale_for_mem_enc),
        sigmoid_bias=float(model.sigmoid_bias_for_mem_enc),
        stability_delta=float(getattr(dec, "dynamic_multimask_stability_delta", 0.05)),
        stability_thresh=float(getattr(dec, "dynamic_multimask_stability_thresh", 0.98)),
        mem_dim=int(model.mem_dim),
        hidden_dim=int(model.hidden_dim),
        multimask_output_in_sam=bool(model.multimask_output_in_sam),
        multimask_output_for_tracking=bool(model.multimask_output_for_tracking),
        multimask_min_pt_num=int(model.multimask_min_pt_num),
        multimask_max_pt_num=int(model.multimask_max_pt_num),
        use_multimask_token_for_obj_ptr=bool(model.use_multimask_token_for_obj_ptr),
        image_size=int(model.image_size),
    )


def sam2_constants(model) -> Dict[str, np.ndarray]:
    def arr(t):
        return t.detach().float().cpu().numpy()

    c = {
        "no_mem_embed": arr(model.no_mem_embed).reshape(1, 1, -1),
        "maskmem_tpos_enc": arr(model.maskmem_tpos_enc),
    }
    if model.proj_tpos_enc_in_obj_ptrs:
        c["obj_ptr_tpos_proj_weight"] = arr(model.obj_ptr_tpos_proj.weight)
        c["obj_ptr_tpos_proj_bias"] = arr(model.obj_ptr_tpos_proj.bias)
    if getattr(model, "no_obj_embed_spatial", None) is not None:
        c["no_obj_embed_spatial"] = arr(model.no_obj_embed_spatial)
    if hasattr(model, "mask_downsample"):
        c["mask_downsample_weight"] = arr(model.mask_downsample.weight)
        c["mask_downsample_bias"] = arr(model.mask_downsample.bias)
    return c


def _image_input(image: Optional[str], size: int) -> np.ndarray:
    from cobgs.masks.images import load_rgb, to_model_input
    from cobgs.masks.manifest import Preprocess

    if image is None:  # a synthetic frame: smooth gradients and a bright disc
        yy, xx = np.mgrid[0:size, 0:size] / size
        disc = ((xx - 0.55) ** 2 + (yy - 0.45) ** 2 < 0.04).astype(np.float64)
        rgb = np.stack([0.3 + 0.6 * disc, 0.2 + 0.5 * xx, 0.4 + 0.4 * yy], -1)
        rgb = (np.clip(rgb, 0, 1) * 255).astype(np.uint8)
    else:
        rgb = load_rgb(image)
    return to_model_input(rgb, Preprocess(size_hw=(size, size)))


def export_sam2(
    config: str,
    checkpoint: Optional[str],
    out_dir: os.PathLike,
    image: Optional[str] = None,
    verify: bool = True,
    model=None,
    video: bool = True,
) -> Dict[str, List[Parity]]:
    """Export, verify and register a SAM2 model in ``out_dir`` (manifest merged).

    Args:
        config: the sam2 hydra config name, e.g. ``configs/sam2.1/sam2.1_hiera_t.yaml``.
        checkpoint: the ``.pt`` file (None: random weights, for tests only).
        image: the image used for verification (default: a synthetic frame).
        model: an already-built ``SAM2Base`` (skips building).
        video: also export the memory graphs (False: an image-only export).

    Returns:
        per graph, the max differences found between onnxruntime and PyTorch.
    """
    import torch

    from cobgs.masks.export import sam2_modules as W

    if model is None:
        model = build_sam2_model(config, checkpoint)
    model = model.float().eval()
    out = Path(out_dir)
    sam = out / "sam2"
    sam.mkdir(parents=True, exist_ok=True)
    size = int(model.image_size)
    img = _image_input(image, size)
    files = {k: out / v for k, v in SAM2_FILES.items()}
    written: List[Path] = []
    report: Dict[str, List[Parity]] = {}
    try:
        with torch.no_grad():
            enc = W.ImageEncoder(model)
            export_graph(enc, (torch.from_numpy(img),), files["image_encoder"], ["image"],
                         ["vision_feats", "vision_pos_embed", "high_res_feats_0",
                          "high_res_feats_1"])
            written.append(files["image_encoder"])
            feats, pos, hr0, hr1 = (t.numpy() for t in enc(torch.from_numpy(img)))
            if verify:
                report["image_encoder"] = verify_graph(
                    files["image_encoder"], enc, {"image": img},
                    ["vision_feats", "vision_pos_embed", "high_res_feats_0", "high_res_feats_1"],
                    atol=1e-3, rtol=1e-3)

            dec = W.MaskDecoder(model)
            embed = feats + model.no_mem_embed.detach().numpy().reshape(1, -1, 1, 1)
            box = np.array([[[0.3 * size, 0.25 * size], [0.8 * size, 0.7 * size]]], np.float32)
            dec_in = {
                "image_embed": embed.astype(np.float32), "high_res_feats_0": hr0,
                "high_res_feats_1": hr1, "point_coords": box,
                "point_labels": np.array([[2, 3]], np.float32),
                "mask_input": np.zeros((1, 1, size // 4, size // 4), np.float32),
                "has_mask_input": np.zeros(1, np.float32),
            }
            dec_out = ["low_res_masks", "iou_predictions", "obj_ptr", "object_score_logits"]
            export_graph(dec, tuple(torch.from_numpy(v) for v in dec_in.values()),
                         files["mask_decoder"], list(dec_in), dec_out,
                         {"point_coords": {1: "num_points"}, "point_labels": {1: "num_points"}})
            written.append(files["mask_decoder"])
            if verify:
                report["mask_decoder"] = verify_graph(files["mask_decoder"], dec, dec_in,
                                                      dec_out, atol=1e-2, rtol=1e-3)
                # and with one positive point and no box (another prompt length)
                one = dict(dec_in, point_coords=box[:, :1] + 10,
                           point_labels=np.ones((1, 1), np.float32))
                report["mask_decoder"] += verify_graph(files["mask_decoder"], dec, one,
                                                       dec_out, atol=1e-2, rtol=1e-3)
            masks = dec(*[torch.from_numpy(v) for v in dec_in.values()])[0].numpy()

            if video:
                mem_enc = W.MemoryEncoder(model)
                high = torch.nn.functional.interpolate(torch.from_numpy(masks[:, :1]),
                                                       size=(size, size), mode="bilinear",
                                                       align_corners=False)
                mask_for_mem = ((high > 0).float() * 20.0 - 10.0).numpy()
                me_in = {"pix_feat": feats, "mask_for_mem": mask_for_mem,
                         "object_score_logits": np.array([[1.5]], np.float32)}
                me_out = ["maskmem_features", "maskmem_pos_enc"]
                export_graph(mem_enc, tuple(torch.from_numpy(v) for v in me_in.values()),
                             files["memory_encoder"], list(me_in), me_out)
                written.append(files["memory_encoder"])
                if verify:
                    report["memory_encoder"] = verify_graph(files["memory_encoder"], mem_enc,
                                                            me_in, me_out, atol=1e-3, rtol=1e-3)
                mf, mp = (t.numpy() for t in mem_enc(*[torch.from_numpy(v)
                                                       for v in me_in.values()]))

                attn = W.MemoryAttention(model)
                c = feats.shape[1]
                tok = lambda a: np.ascontiguousarray(  # noqa: E731
                    a.reshape(a.shape[1], -1).T[:, None, :])
                rng = np.random.default_rng(0)
                mem = np.concatenate([tok(mf), tok(mf) * 0.5])
                mem_pos = np.concatenate([tok(mp), tok(mp)])
                ptr = rng.standard_normal((8, 1, mf.shape[1])).astype(np.float32)
                at_in = {"curr": tok(feats), "curr_pos": tok(pos), "memory": mem,
                         "memory_pos": mem_pos, "obj_ptr_tokens": ptr,
                         "obj_ptr_pos": np.zeros_like(ptr)}
                export_graph(attn, tuple(torch.from_numpy(v) for v in at_in.values()),
                             files["memory_attention"], list(at_in), ["pix_feat_with_mem"],
                             {"memory": {0: "num_memory_tokens"},
                              "memory_pos": {0: "num_memory_tokens"},
                              "obj_ptr_tokens": {0: "num_pointer_tokens"},
                              "obj_ptr_pos": {0: "num_pointer_tokens"}})
                written.append(files["memory_attention"])
                if verify:
                    report["memory_attention"] = verify_graph(
                        files["memory_attention"], attn, at_in, ["pix_feat_with_mem"],
                        atol=1e-3, rtol=1e-3)
                    # other memory / pointer counts than traced: the axes are dynamic
                    three = dict(at_in, memory=np.concatenate([mem, tok(mf)]),
                                 memory_pos=np.concatenate([mem_pos, tok(mp)]),
                                 obj_ptr_tokens=ptr[:4], obj_ptr_pos=np.zeros_like(ptr[:4]))
                    report["memory_attention"] += verify_graph(
                        files["memory_attention"], attn, three, ["pix_feat_with_mem"],
                        atol=1e-3, rtol=1e-3)
                    _check_memory_attention_upstream(model, attn, three, c)

        np.savez(files["constants"], **sam2_constants(model))
    except BaseException:
        remove_partial(written)
        raise
    entry = sam2_manifest_dict(Sam2Layout(), sam2_host_config(model), video=video)
    entry["note"] = f"exported by cobgs from {checkpoint or 'random weights'} ({config})"
    write_manifest(out, {"sam2": entry})
    return report


def _check_memory_attention_upstream(model, wrapper, feeds, channels) -> None:
    """The real-valued rotary rewrite must match upstream's complex-number forward."""
    import torch

    t = {k: torch.from_numpy(v) for k, v in feeds.items()}
    with torch.no_grad():
        mem = torch.cat([t["memory"], t["obj_ptr_tokens"]])
        pos = torch.cat([t["memory_pos"], t["obj_ptr_pos"]])
        ref = model.memory_attention(curr=[t["curr"]], curr_pos=[t["curr_pos"]], memory=mem,
                                     memory_pos=pos,
                                     num_obj_ptr_tokens=t["obj_ptr_tokens"].shape[0])
        ref = ref.permute(1, 2, 0).reshape(1, channels, 64, 64)
        got = wrapper(*t.values())
    diff = float((ref - got).abs().max())
    if not diff <= 1e-3 * max(1.0, float(ref.abs().max())):
        raise ExportError(f"memory attention rewrite differs from sam2's own forward by {diff}")
    log.info("memory attention: rewrite vs sam2 forward max diff %.3g", diff)


__all__ = ["export_sam2", "build_sam2_model", "sam2_host_config", "sam2_constants",
           "ExportError", "asdict"]
