"""The picture sets of the report: which view, which masks and renders, per scene x object.

Reads the run data (held-out images and GT from the ``heldout`` stage, masks and renders
from ``segment``, per-view numbers from ``evaluate``) and hands the arrays to
:func:`reports.pictures.compose`.
"""

from __future__ import annotations

from cobgs.configs import Files
from pathlib import Path
from typing import Optional

from . import fmt
from .methods import reference_of
from .collect import RunData
from .pictures import MethodPictures, PictureSet, compose, read_mask, read_rgb, slug


#: segment's mask folder per ``mask_render`` of an evaluate row: the overlay must show the
#: mask that was scored (exact protocol: the visible mask; NVOS / LERF-mask: object only)
MASK_FOLDERS = {"visible": Files.PRED_VISIBLE, "object_only": Files.PRED_MASKS}


def scored_mask_folder(row: Optional[dict]) -> str:
    return MASK_FOLDERS.get(str((row or {}).get("mask_render", "object_only")), Files.PRED_MASKS)


def _turntables(data: RunData, ps: PictureSet, rs: dict, scene, root: Path, base: str, frames: int,
                cameras: dict) -> None:
    """Orbit GIFs of each method's object alone and scene without it (cobgs.render.turntable)."""
    from cobgs.render.turntable import object_turntables

    if scene is None or scene.dataset_dir is None:
        return
    if scene.name not in cameras:
        cameras[scene.name] = data.cameras(scene)
    refs, bg = cameras[scene.name]
    for mp in ps.methods:
        r = rs.get(mp.method)
        if r is None or r.segment_dir is None:
            continue
        urls = {k: f"{base}/{slug(mp.method)}_turn_{k}.gif" for k in ("object", "removed")}
        seg = Path(r.segment_dir)
        for kind in object_turntables(seg / Files.OBJECT_PLY, seg / Files.BACKGROUND_PLY, refs, bg, frames,
                                      {k: root / u for k, u in urls.items()}):
            mp.files[f"turn_{kind}"] = urls[kind]


def picture_sets(data: RunData, infos: dict, root: Path, turntables: int = 0) -> list[PictureSet]:
    """The picture grid of every scene x object; ``turntables`` > 0 adds orbit GIFs with
    that many frames per method (rendered here, on the CPU: opt-in for large reports)."""
    ref = reference_of(infos)
    cameras: dict = {}
    order = ([ref] if ref else []) + [m for m in data.methods if m != ref]
    sets = []
    pairs = []
    for r in data.results:
        if (r.scene, r.object) not in pairs:
            pairs.append((r.scene, r.object))
    for scene, obj in pairs:
        rs = {r.method: r for r in data.results if r.scene == scene and r.object == obj}
        held = data.scenes[scene].heldout.get(obj) if scene in data.scenes else None
        notes = []
        view, image, gt = None, None, None
        if held is not None:
            views = held.info.get("views") or []
            with_gt = [v for v in views if v.get("gt")]
            pick = (with_gt or views or [None])[0]
            if pick is not None:
                view = pick["name"]
                image = read_rgb(held.folder / pick["image"])
                gt = read_mask(held.folder / pick["gt"]) if pick.get("gt") else None
                if with_gt:
                    notes.append(f"Held-out view {view}: the first of the {len(with_gt)} held-out view(s) with a "
                                 f"ground-truth mask that the heldout stage wrote (not chosen by result).")
                else:
                    notes.append(f"Held-out view {view}: the first of the {len(views)} held-out view(s); none "
                                 "has a ground-truth mask (e.g. your own photos), so there is no error "
                                 "overlay or crop: judge the predicted mask and the renders by eye.")
        else:
            notes.append("No held-out image or ground truth: the heldout stage has not run for this object "
                         f"(`cobgs run {data.workflow.path} --only heldout`); predicted masks and renders only.")
            for m in order:
                seg = rs[m].segment if m in rs else None
                if seg and seg.get("views"):
                    view = sorted(seg["views"])[0]
                    break
        if view is None:
            continue
        if any((r.row or {}).get("mask_render") == "visible" for r in rs.values()):
            notes.append("Predicted masks are the object's visible part (every Gaussian rendered, so "
                         "occluders hide the object as they do in the ground truth): the mask the "
                         "evaluate stage scored for this protocol.")
        ps = PictureSet(scene=scene, object=obj, view=view, notes=notes, id=slug(f"{scene}/{obj}"))
        preds, renders = {}, {}
        for m in order:
            if m not in rs:
                continue
            r = rs[m]
            mp = MethodPictures(m, infos[m].kind_label if m in infos else m)
            pv = r.per_view.get(view) or {}
            mp.iou, mp.biou = fmt.finite(pv.get("iou")), fmt.finite(pv.get("biou"))
            if r.segment_dir is not None:
                f = Path(r.segment_dir) / scored_mask_folder(r.row) / f"{view}.png"
                if f.is_file():
                    preds[m] = read_mask(f)
                for kind, folder in (("object", Files.OBJECT_RENDERS), ("removed", Files.REMOVED_RENDERS)):
                    f = Path(r.segment_dir) / folder / f"{view}.png"
                    if f.is_file():
                        renders.setdefault(m, {})[kind] = read_rgb(f)
            if m not in preds:
                p = r.problem
                mp.note = f"{p.state} at {p.stage}" if p else "no segmentation of this view"
            ps.methods.append(mp)
        base = f"img/{slug(scene)}/{slug(obj)}/{slug(view)}"
        compose(ps, image, gt, preds, renders, root / base, base)
        if turntables > 0:
            _turntables(data, ps, rs, data.scenes.get(scene), root, f"img/{slug(scene)}/{slug(obj)}", turntables,
                        cameras)
        sets.append(ps)
    return sets
