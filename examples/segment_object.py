"""Segment one object of a trained 3DGS scene with COB-GS through the library alone.

    python examples/segment_object.py SCENE_FOLDER SCENE.ply OBJECT --out DIR

SCENE_FOLDER is any layout cobgs reads (transforms.json, COLMAP, LLFF, NeRF-synthetic) with
the object's masks in masks/OBJECT/<view>.png; SCENE.ply a standard 3DGS PLY trained on it.
"""
import argparse
from pathlib import Path

import cv2

from cobgs.data.readers import read_scene
from cobgs.gaussians.ply import load_ply, save_ply
from cobgs.refine.alternation import masks_for, refine
from cobgs.configs import RefineConfig
from cobgs.refine.segment import extract, render_object_mask

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("scene"), ap.add_argument("ply"), ap.add_argument("object")
ap.add_argument("--out", default="segmented")
ap.add_argument("--scene-type", default="forward", choices=("forward", "360"))
ap.add_argument("--stage-length", type=float, default=2.0, help="mask / texture stage length, in views")
a = ap.parse_args()

scene = read_scene(a.scene)                       # posed views, masks, held-out split
model = load_ply(a.ply)                           # the trained Gaussians
config = RefineConfig(scene_type=a.scene_type, stage_length_views=a.stage_length)
result = refine(model, scene.train, masks_for(scene.train, a.object), scene.extent, config,
                background=scene.background, object_name=a.object)   # COB-GS (docs/method.md §2)
out = Path(a.out)
out.mkdir(parents=True, exist_ok=True)
save_ply(out / "object.ply", extract(result, "foreground"))     # the object alone, standard 3DGS
save_ply(out / "removed.ply", extract(result, "background"))    # the scene without it
for view in scene.test:                                          # its mask on the held-out views
    cv2.imwrite(str(out / f"{view.name}.png"), render_object_mask(result, view.camera).numpy().astype("uint8") * 255)
print(f"{int(result.foreground.sum())} of {len(result.model)} Gaussians are {a.object!r}; written to {out}")
