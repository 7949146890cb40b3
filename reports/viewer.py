"""The 3D viewers of the report: per scene x object, each method's segmentation as
quantised Gaussians (:mod:`cobgs.render.splat_pack`) for ``static/viewer.js``.

A method's model is the segment stage's ``object.ply`` (label 1) followed by its
``background.ply`` (label 0): together, the refined scene as the segmentation split it, so
one embedded model serves the four modes of the viewer (object alone, object removed,
labels, whole scene). The data go to ``viewer/<scene>/<object>/<method>.js`` as base64 in a
script (browsers refuse ``fetch`` of ``file://`` URLs; a script loads from anywhere), loaded
only when a viewer is opened.

Size cap: the payload of a scene (all its objects and methods) is held under
``max_mb``; when it is over, every model of the scene keeps the same fraction of its
Gaussians, the most opaque x largest first (:func:`cobgs.render.splat_pack.keep_order`), and the
page says so.
"""

from __future__ import annotations

from cobgs.configs import Files
import base64
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

from .pictures import slug

#: default cap of the viewer payload per scene (raw bytes; base64 on disk is 4/3 of it)
DEFAULT_MAX_MB = 8.0
MODES = (("object", "object alone"), ("removed", "object removed"), ("labels", "labels"),
         ("scene", "whole scene"))


@dataclass
class ViewerSet:
    """What the page needs for one viewer (the template reads ``config`` as JSON)."""

    config: dict
    methods: list = field(default_factory=list)  # (method, label) in the picture grid's order
    notes: list = field(default_factory=list)
    modes: tuple = MODES


def _camera_record(cam) -> dict:
    K = cam.K.double()
    return {"name": cam.name, "w": int(cam.width), "h": int(cam.height),
            "K": [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])],
            "w2c": [float(v) for v in cam.viewmat.double().reshape(-1)]}


def _up(cameras) -> list:
    import torch

    ups = torch.stack([-c.c2w.double()[:3, 1] for c in cameras])
    return [float(v) for v in torch.nn.functional.normalize(ups.mean(0), dim=0)]


def _load(seg_dir: Path):
    """(model, labels, object count) of a segment artifact: its object's Gaussians, then
    the background's (labels 1, then 0); None without the two PLYs."""
    import numpy as np
    import torch

    from cobgs.gaussians.model import CORE, GaussianModel
    from cobgs.gaussians.ply import load_ply

    obj_p, bg_p = seg_dir / Files.OBJECT_PLY, seg_dir / Files.BACKGROUND_PLY
    if not (obj_p.is_file() and bg_p.is_file()):
        return None
    parts = [load_ply(obj_p), load_ply(bg_p)]
    model = GaussianModel(*(torch.cat([m.data[k].detach() for m in parts]) for k in CORE))
    labels = np.concatenate([np.ones(len(parts[0]), np.uint8), np.zeros(len(parts[1]), np.uint8)])
    return model, labels, len(parts[0])


def _script_head(key: str) -> str:
    """How a viewer data file starts (written by viewer_sets, read back by embedded)."""
    return "(window.COBGS_SPLATS = window.COBGS_SPLATS || {})[" + json.dumps(key) + '] = "'


def viewer_sets(data, pictures: list, root: Path, max_mb: Optional[float] = DEFAULT_MAX_MB) -> dict:
    """Write every picture set's viewer data under ``root/viewer`` and return
    {picture set id: :class:`ViewerSet`} (sets without any segmented model have none).

    Args:
        data: :class:`reports.collect.RunData`.
        pictures: the :class:`reports.pictures.PictureSet` list of the page.
        max_mb: payload cap per scene in MB (10^6 bytes); None = no cap.
    """
    import torch

    from cobgs.render import splat_pack
    from cobgs.refine.segment import subset
    from cobgs.render.turntable import object_center

    results = {(r.scene, r.object, r.method): r for r in data.results}

    by_scene: dict = {}
    for ps in pictures:
        by_scene.setdefault(ps.scene, []).append(ps)
    out = {}
    for scene, sets in by_scene.items():
        sc = data.scenes.get(scene)
        if sc is None or sc.dataset_dir is None:
            continue
        loaded = {}  # (ps.id, method) -> (model, labels, n_object)
        for ps in sets:
            for mp in ps.methods:
                r = results.get((ps.scene, ps.object, mp.method))
                if r is None or r.segment_dir is None:
                    continue
                got = _load(Path(r.segment_dir))
                if got is not None and len(got[0]):
                    loaded[(ps.id, mp.method)] = got
        if not loaded:
            continue
        cams, background = data.cameras(sc)
        cam_records = [_camera_record(c) for c in cams]
        up = _up(cams)
        total = sum(len(m) for m, _, _ in loaded.values())
        cap = None if max_mb is None else int(max_mb * 1e6)
        keep_n = splat_pack.budget_count(total, cap)
        fraction = keep_n / total if total else 1.0
        for ps in sets:
            models, methods, notes = {}, [], []
            center = None
            for mp in ps.methods:
                got = loaded.get((ps.id, mp.method))
                if got is None:
                    continue
                model, labels, n_obj = got
                if center is None and n_obj:  # the orbit's pivot: the first method's object
                    center = [float(v) for v in object_center(subset(model, torch.arange(n_obj), extras=[]))]
                keep = None
                if fraction < 1.0:
                    order = splat_pack.keep_order(model)
                    keep = order[:max(1, int(len(model) * fraction))]
                    keep.sort()
                header, payload = splat_pack.pack(model, labels, keep)
                key = f"{ps.scene}/{ps.object}/{mp.method}"
                rel = f"viewer/{slug(ps.scene)}/{slug(ps.object)}/{slug(mp.method)}.js"
                dst = root / rel
                dst.parent.mkdir(parents=True, exist_ok=True)
                dst.write_text(_script_head(key) + base64.b64encode(payload).decode("ascii") + "\";\n",
                               encoding="ascii")
                n_obj_kept = n_obj if keep is None else int((keep < n_obj).sum())
                models[mp.method] = {"src": rel, "key": key, "header": header, "total": len(model),
                                     "object_total": n_obj, "object_kept": n_obj_kept, "bytes": len(payload)}
                methods.append((mp.method, mp.label))
            if not models:
                continue
            if center is None:  # every method's object is empty: orbit the scene's Gaussians
                center = [float(v) for v in object_center(loaded[(ps.id, methods[0][0])][0])]
            names = [m for m, _ in methods]
            if fraction < 1.0:
                notes.append(f"Subsampled: scene {scene} holds {total:,} Gaussians over its objects and methods, "
                             f"{total * splat_pack.BYTES_PER_GAUSSIAN / 1e6:.1f} MB packed, over the viewer's cap of "
                             f"{max_mb:g} MB per scene; each model here keeps {100 * fraction:.1f}% of its "
                             "Gaussians, the most opaque x largest first (cobgs report --viewer-mb raises the cap).")
            config = {"id": ps.id, "background": [float(v) for v in background], "center": center, "up": up,
                      "cameras": cam_records, "models": models, "left": names[0],
                      "right": names[1] if len(names) > 1 else None, "mode": "object",
                      "bytes_per_gaussian": splat_pack.BYTES_PER_GAUSSIAN}
            out[ps.id] = ViewerSet(config=config, methods=methods, notes=notes)
    return out


def embedded(report_dir: Path, record: dict) -> tuple[dict, bytes]:
    """(header, payload) of one embedded model, read back from a built report: what the
    page's viewer decodes (for tests and benchmarks)."""
    text = (Path(report_dir) / record["src"]).read_text(encoding="ascii")
    head = _script_head(record["key"])
    if not text.startswith(head) or not text.rstrip().endswith('";'):
        raise ValueError(f"{record['src']}: not a viewer data file of {record['key']!r}")
    return record["header"], base64.b64decode(text[len(head):text.rstrip().rindex('"')])


def configs(report_dir: Path) -> list[dict]:
    """The viewer configurations embedded in a built report's index.html."""
    import re

    page = (Path(report_dir) / "index.html").read_text(encoding="utf-8")
    return [json.loads(m) for m in
            re.findall(r'<script type="application/json" class="viewer-data">(.*?)</script>', page, re.S)]
