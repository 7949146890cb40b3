"""``cobgs export-onnx sam2|gdino``: write the ONNX models mask generation runs on.

Users run this where torch, the model code and the checkpoints are; it writes the files
of the ONNX contract plus ``manifest.json`` and verifies the graphs against PyTorch on
one image before reporting success. Imports stay inside the command functions.
"""

from __future__ import annotations


def _sam2(args) -> int:
    import logging

    from cobgs.masks.export.sam2_export import export_sam2

    logging.basicConfig(level=logging.INFO, format="%(message)s")
    report = export_sam2(args.config, args.checkpoint, args.out, image=args.image,
                         verify=not args.no_verify, video=not args.image_only)
    _print_report("SAM2", args.out, report)
    return 0


def _gdino(args) -> int:
    import logging

    from cobgs.masks.export.gdino_export import export_gdino, parse_size
    from cobgs.masks.manifest import keep_aspect_size

    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.for_frame is not None:
        size = keep_aspect_size(*parse_size(args.for_frame))
        print(f"frames of {args.for_frame[0]}x{args.for_frame[1]} enter Grounding DINO at {size[0]}x{size[1]} "
              "(short side 800, long side at most 1333, aspect kept): tracing at that size")
    else:
        size = parse_size(args.size)
    report = export_gdino(args.out, size, config=args.config,
                          checkpoint=args.checkpoint, caption=args.caption, image=args.image,
                          verify=not args.no_verify, vocab_path=args.vocab,
                          resize="stretch" if args.stretch else "keep_aspect", bert=args.bert)
    _print_report("Grounding DINO", args.out, {"groundingdino": report})
    return 0


def _print_report(what, out, report) -> None:
    for graph, parities in report.items():
        for p in parities:
            print(f"  {graph:18s} {p.name:22s} max |onnxruntime - torch| = {p.max_abs:.3g}")
    verified = "verified against PyTorch" if report and any(report.values()) else "NOT verified"
    print(f"{what} exported to {out} ({verified}); manifest: {out}/manifest.json")


def register(sub) -> None:
    p = sub.add_parser("export-onnx", help="export SAM2 / Grounding DINO to the ONNX models "
                                           "mask generation uses (needs torch + model code)")
    models = p.add_subparsers(dest="model", metavar="MODEL")
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])

    s = models.add_parser("sam2", help="SAM2 video model -> 4 graphs + constants")
    s.add_argument("--config", required=True,
                   help="sam2 hydra config name, e.g. configs/sam2.1/sam2.1_hiera_l.yaml")
    s.add_argument("--checkpoint", required=True, help="the SAM2 .pt checkpoint")
    s.add_argument("--out", required=True, help="model folder (manifest.json is merged)")
    s.add_argument("--image", help="image used to verify the export (default: synthetic)")
    s.add_argument("--image-only", action="store_true",
                   help="encoder + decoder only (single-frame prompting, no propagation)")
    s.add_argument("--no-verify", action="store_true", help="skip the onnxruntime check")
    s.set_defaults(func=_sam2)

    g = models.add_parser("gdino", help="Grounding DINO -> one graph + vocab.txt")
    g.add_argument("--config", required=True, help="the GroundingDINO_*_cfg.py file")
    g.add_argument("--checkpoint", required=True, help="the Grounding DINO .pth checkpoint")
    g.add_argument("--out", required=True, help="model folder (manifest.json is merged)")
    size = g.add_mutually_exclusive_group()
    size.add_argument("--size", type=int, nargs=2, default=[800, 1200],
                      metavar=("HEIGHT", "WIDTH"), help="fixed input size to trace at (default 800 1200: "
                      "frames of 2:3 aspect, e.g. 1200x800 landscape... see --for-frame)")
    size.add_argument("--for-frame", type=int, nargs=2, metavar=("HEIGHT", "WIDTH"),
                      help="trace at the size Grounding DINO gives frames of this size (aspect kept, "
                           "short side 800, long side at most 1333), e.g. 756 1008 -> 800x1066")
    g.add_argument("--stretch", action="store_true",
                   help="let the host stretch frames of any aspect to the traced size (upstream keeps "
                        "the aspect: detections then differ from its)")
    g.add_argument("--vocab", help="BERT vocab.txt (default: from the model's tokenizer)")
    g.add_argument("--bert", help="a local bert-base-uncased folder (config.json, vocab.txt, weights) for "
                                  "the text encoder, instead of fetching it from a model hub")
    g.add_argument("--caption", default="a cat . a remote control .",
                   help="caption used for tracing and verification")
    g.add_argument("--image", help="image used to verify the export (default: random)")
    g.add_argument("--no-verify", action="store_true", help="skip the onnxruntime check")
    g.set_defaults(func=_gdino)
