"""Stage ``heldout``: the held-out images and ground-truth masks the HTML report draws on.

Per scene x object. The evaluation protocols know where each scene keeps its ground truth
(dataset masks, the NVOS target's full-resolution mask, LERF-mask's ``test_mask/``); this
stage writes the held-out view and its GT mask as plain PNGs so that ``cobgs report`` can
draw error overlays from the cache alone, without reading datasets or importing torch.

Output ``heldout``:
  image/<view>.png   the held-out image at the render size (8-bit RGB)
  gt/<view>.png      its GT mask of this object, 0/255, at the size the protocol compares
                     at (NVOS: full resolution); absent where the view has no GT
  heldout.json       format ``cobgs-heldout`` v1: protocol, object, the views written (with
                     sizes and GT areas) and the held-out views left out, with the reason
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from cobgs.configs import Files, check_params
from pipeline import Resources, Stage

from ._common import load_scene, nvos_task, object_name, read_spec, write_json, write_png

FORMAT = "cobgs-heldout"


@dataclass(frozen=True)
class HeldoutParams:
    """Attributes:
        max_views: held-out views written per object (0 = all). Views with a non-empty GT
            mask come first, evenly spaced over the sorted view names, so that LERF-mask
            scenes with dozens of test views keep the report small.
    """

    max_views: int = 3

    RANGES: ClassVar[dict] = {"max_views": "[0, 1e6]"}

    def __post_init__(self) -> None:
        check_params(self)
        if self.max_views < 0:
            raise ValueError(f"max_views must be >= 0, got {self.max_views}")


def _gt_of(spec: dict, obj: str, item_object: str = ""):
    """A function view -> (uint8 0/255 [H, W] GT mask or None, reason when None)."""
    from cobgs.evaluate import protocols as E

    protocol = spec.protocol
    if protocol == "nvos":
        task = nvos_task(spec, item_object, obj)
        return lambda v: ((E.read_mask_u8(task["gt_mask"]), "") if v.name == task["target"]
                          else (None, "not the NVOS target view"))
    if protocol == "lerf_mask":
        paths = {m["view"]: m["path"] for m in spec.lerf_mask["masks"] if m["prompt"] == obj}
        return lambda v: ((E.read_mask_u8(paths[v.name]), "") if v.name in paths
                          else (None, "no GT file"))
    if protocol == "exact":
        return lambda v: ((E.to_u8(v.masks[obj].cpu().numpy()), "") if obj in v.masks
                          else (None, "object not annotated in this view"))
    return lambda v: (None, f"protocol {protocol!r} has no mask GT")


def _pick(names: list[str], k: int) -> list[str]:
    """``k`` names evenly spaced over ``names`` (all of them when k is 0 or enough)."""
    if k == 0 or len(names) <= k:
        return list(names)
    step = (len(names) - 1) / max(1, k - 1)
    return [names[round(i * step)] for i in range(k)] if k > 1 else [names[len(names) // 2]]


def _run(ctx, inputs):
    import numpy as np

    from cobgs.evaluate.protocols import THRESHOLD_U8

    p: HeldoutParams = ctx.params
    spec = read_spec(inputs["dataset"])
    obj = object_name(ctx)
    scene = load_scene(inputs["dataset"], inputs["poses"])
    gt_of = _gt_of(spec, obj, ctx.item["object"])
    views = sorted(scene.test, key=lambda v: v.name)
    gts, skipped = {}, {}
    for v in views:
        g, why = gt_of(v)
        if g is not None:
            g = np.where(g > THRESHOLD_U8, 255, 0).astype(np.uint8)  # binarised as evaluated
            if not g.any():
                g, why = None, "empty GT"
        gts[v.name] = g
        if g is None:
            skipped[v.name] = why
    with_gt = [v.name for v in views if gts[v.name] is not None]
    # A scene without mask GT (texture-only protocol) still gets its held-out images.
    chosen = set(_pick(with_gt if with_gt else [v.name for v in views], p.max_views))
    rows = []
    for v in views:
        if v.name not in chosen:
            skipped.setdefault(v.name, f"beyond max_views={p.max_views}")
            continue
        img = v.image.detach().cpu().numpy()
        write_png(ctx.out_dir / "image" / f"{v.name}.png", img)
        g = gts[v.name]
        row = {"name": v.name, "image": f"image/{v.name}.png", "image_size": [int(img.shape[0]), int(img.shape[1])],
               "gt": None, "gt_size": None, "gt_area_px": None}
        if g is not None:
            write_png(ctx.out_dir / "gt" / f"{v.name}.png", g)
            row.update(gt=f"gt/{v.name}.png", gt_size=[int(g.shape[0]), int(g.shape[1])],
                       gt_area_px=int(np.count_nonzero(g)))
        rows.append(row)
    write_json(ctx.out_dir / Files.HELDOUT, {
        "format": FORMAT, "version": 1, "scene": spec.scene, "object": obj, "object_item": ctx.item["object"],
        "protocol": spec.protocol, "held_out": len(views), "views": rows,
        "skipped": {k: v for k, v in sorted(skipped.items()) if k not in chosen}})
    ctx.log.info("held-out views of %r: %d written (%d with GT) of %d", obj, len(rows),
                 sum(r["gt"] is not None for r in rows), len(views))
    ctx.note(object=obj, views=len(rows), with_gt=sum(r["gt"] is not None for r in rows), held_out=len(views))
    return {"heldout": ctx.out_dir}


STAGE = Stage(
    name="heldout", version=1, run=_run, inputs=("dataset", "poses"), outputs=("heldout",),
    params=HeldoutParams, level=("scene", "object"), resources=Resources(cpus=1),
    description="held-out images and GT masks per object, as PNGs for the HTML report",
)
