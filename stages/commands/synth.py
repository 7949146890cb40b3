"""``cobgs synth`` (render a synthetic scene) and ``cobgs synth-noise`` (corrupt its masks).

Only the standard library is imported here; numpy and the generator load when a command
runs, so ``cobgs --help`` stays fast. The preset names and noise options are listed here
for the same reason; tests/data/test_synthetic.py checks they match the library.
"""

from __future__ import annotations

import time

PRESET_NAMES = ("demo", "forward", "orbit")

# (MaskNoiseParams field, type, help) for `cobgs synth-noise`.
NOISE_OPTIONS = (
    ("drop_rate", float, "probability that a mask is replaced by an empty one"),
    ("morph_rate", float, "probability that a mask is eroded or dilated"),
    ("morph_max_px", int, "largest erosion/dilation radius (px)"),
    ("dilate_fraction", float, "share of dilations among erosions/dilations"),
    ("jitter_rate", float, "probability that a mask's boundary is jittered"),
    ("jitter_amplitude_px", float, "largest boundary displacement of the jitter (px)"),
    ("jitter_scale_px", float, "correlation length of the jitter along the boundary (px)"),
    ("blob_rate", float, "probability that spurious blobs are added to a mask"),
    ("blob_count_max", int, "most blobs added to one mask"),
    ("blob_radius_min_px", int, "smallest blob radius (px)"),
    ("blob_radius_max_px", int, "largest blob radius (px)"),
)


def _size(text: str):
    import argparse

    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT like 320x240, got {text!r}")
    return w, h


def _synth(args) -> int:
    from cobgs.data.synth.scene import generate_scene

    w, h = args.size if args.size else (None, None)
    t0 = time.perf_counter()
    out = generate_scene(args.out, args.preset, args.seed, overwrite=args.overwrite,
                         progress=not args.quiet, width_px=w, height_px=h,
                         num_views=args.views, supersampling=args.supersampling,
                         workers=args.workers)
    print(f"synthetic scene {args.preset!r} (seed {args.seed}) written to {out} "
          f"in {time.perf_counter() - t0:.1f} s")
    return 0


def _synth_noise(args) -> int:
    from pathlib import Path

    from cobgs.data.mask_noise import noise_mask_folder
    from cobgs.configs import MaskNoiseParams

    src = Path(args.masks)
    if (src / "masks").is_dir() and (src / "transforms.json").is_file():
        src = src / "masks"  # a scene folder was given
    given = {name: getattr(args, name) for name, _, _ in NOISE_OPTIONS
             if getattr(args, name) is not None}
    params = MaskNoiseParams(seed=args.seed, **given)
    log = noise_mask_folder(src, args.out, params, overwrite=args.overwrite,
                            progress=not args.quiet)
    n = sum(len(v) for v in log.values())
    dropped = sum(r["dropped"] for v in log.values() for r in v.values())
    print(f"{n} noisy masks ({dropped} dropped) of {len(log)} objects written to {args.out}")
    return 0


def register(sub) -> None:
    p = sub.add_parser("synth", help="render a synthetic multi-object scene with exact masks",
                       description="Render a synthetic scene (images, exact per-object masks, "
                       "coverage, transforms.json, scene.json) into a new folder.")
    p.add_argument("--preset", choices=PRESET_NAMES, default="demo",
                   help="scene and capture (default: demo)")
    p.add_argument("--out", required=True, help="output folder (must not exist or be empty)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    p.add_argument("--size", type=_size, default=None, metavar="WxH",
                   help="override the preset's image size")
    p.add_argument("--views", type=int, default=None, help="override the number of views")
    p.add_argument("--supersampling", type=int, default=None, metavar="S",
                   help="override the S x S subsamples per pixel")
    p.add_argument("--workers", type=int, default=1,
                   help="processes rendering views in parallel, 0 = one per core (default: 1); "
                   "the output does not depend on it")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing scene folder that synth wrote (anything else is refused)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_synth)

    q = sub.add_parser("synth-noise", help="write a noisy copy of a masks folder",
                       description="Corrupt exact masks like SAM-style tracking does (dropped "
                       "frames, erosion/dilation, boundary jitter, spurious blobs). Options left "
                       "unset keep the MaskNoiseParams defaults; the values used are written to "
                       "<out>/noise.json.")
    q.add_argument("masks", help="masks folder (<object>/<stem>.png) or a scene folder")
    q.add_argument("--out", required=True, help="output masks folder")
    q.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    for name, typ, text in NOISE_OPTIONS:
        q.add_argument("--" + name.replace("_", "-"), dest=name, type=typ, default=None, help=text)
    q.add_argument("--overwrite", action="store_true",
                   help="replace an existing mask folder that synth-noise wrote (anything else is refused)")
    q.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    q.set_defaults(func=_synth_noise)
