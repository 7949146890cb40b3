"""Where an object's training-view masks come from: one class per route behind one registry.

A :class:`MaskSource` is everything the pipeline needs of a route, in one object: its name
(``masks.source``), the params it reads (``reads``: the cache key keeps only those, so tuning one
route never recomputes another's masks), its ``version`` (bumped when its behaviour changes,
instead of the stage's, which would recompute every route), the models it needs, the words the
report uses for it (:meth:`~MaskSource.route`), its load-time check and
:meth:`~MaskSource.masks` on a :class:`MaskRequest`. Routes:

  files   the dataset's own masks (``masks/<object>/``, Blender alpha), or a folder of per-view
          mask images named after the views (an object's ``mask_dir``, or ``masks.files_root``'s
          folder of it): any resolution, resized NEAREST, a pixel above ``files_threshold``;
  noisy   the same, corrupted by :mod:`cobgs.data.mask_noise` (robustness runs);
  onnx    two-stage text prompting, Grounding DINO + SAM2 (:func:`cobgs.masks.api.generate_masks`);
  nvos    NVOS scribbles on the reference view -> SAM2 -> propagation;
  points  clicks (:mod:`cobgs.masks.clicks`) -> SAM2 on each prompted frame -> propagation;
  prompt_clicks  SPIn-NeRF: clicks placed inside the prompt view's GT mask -> SAM2 -> propagation
          (the route a user has: a few clicks on one view).

A new route is one class here (its algorithm in a module of its own) and one line of
:data:`SOURCES` (docs/pipeline.md, "Adding a mask source"). This module imports nothing
heavy at load: the stage's params check a route without torch or onnxruntime.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional, Sequence

from cobgs.errors import DataError, InputError

#: The image files a mask folder may hold.
MASK_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff")

MODELS_HELP = ("masks.source {source!r} needs masks.models_dir, which is not set: export the models "
               "with `cobgs export-onnx sam2 ...` (and `gdino` for text prompts) and pass the folder "
               "with `--set masks.models_dir=DIR` or `models_dir = ...` under [params.masks]. "
               "To run without models, read masks from files: `--set masks.source=files` (with "
               "`--set masks.files_root=DIR` for a folder of per-object mask folders, such as COB-GS's "
               "released NVOS masks); or, once the models exist, click prompts with "
               "`--set masks.source=points --set masks.points_file=FILE`")


@dataclass(frozen=True)
class MaskRequest:
    """What a route needs to make one object's masks.

    Attributes:
        object: the dataset object (its mask folder's name, the default prompt).
        item: the object axis value's own name.
        views: the training views (:class:`cobgs.data.scene.View`: name, image path, size,
            the dataset's masks).
        spec: the scene's record (:class:`cobgs.data.spec.DatasetSpec`).
        params: the masks params (``source``, ``models_dir``, ``noise``, ``two_stage``, ...).
        mask_dir: the object's folder of per-view masks, where it has one.
        prompt: the text prompt (default: the object's name, ``_`` read as a space).
        click_names: the names a click file's entry of this object is looked up by.
        scratch: a private folder for what the generators write.
        device: where the models run ("cpu", "cuda", "cuda:1").
    """

    object: str
    item: str
    views: Sequence
    spec: Any
    params: Any
    mask_dir: Optional[Path] = None
    prompt: str = ""
    click_names: tuple[str, ...] = ()
    scratch: Optional[Path] = None
    device: str = "cpu"


class MaskSource:
    """The protocol (module docstring); subclasses set the class attributes and :meth:`masks`."""

    name: str = ""
    #: the params fields this route reads (its cache key holds these and ``source`` only)
    reads: tuple[str, ...] = ()
    version: int = 1
    #: the models of a manifest it needs ("sam2", "gdino")
    models: tuple[str, ...] = ()
    #: it reads a folder of mask files (``mask_dir``, ``files_root``)
    reads_folders: bool = False

    def route(self, from_folder: bool) -> str:
        """How the masks were made, in the words reports use."""
        raise NotImplementedError

    def key_params(self, params_json: dict) -> dict:
        """What of the masks params enters this route's cache key."""
        out = {"source": self.name, **{k: params_json[k] for k in self.reads}}
        if self.version != 1:
            out["route_version"] = self.version
        return out

    def check(self, params: Any) -> None:
        """Checks when the workflow loads, before any task runs (a model folder's manifest).

        Raises:
            ValueError: naming the setting and the fix.
        """
        if not self.models:
            return
        if params.models_dir is None:
            raise ValueError(MODELS_HELP.format(source=self.name))
        if not Path(params.models_dir).is_dir():
            raise ValueError(f"masks.models_dir {params.models_dir} does not exist (source {self.name!r} needs "
                             "the ONNX model folder)")
        from cobgs.errors import ModelError
        from cobgs.masks.manifest import load_manifest

        try:
            manifest = load_manifest(params.models_dir)
        except ModelError as exc:
            raise ValueError(f"masks.models_dir: {exc}") from None
        lacking = [n for n in self.models if getattr(manifest, n) is None]
        if lacking:
            names = {"sam2": "SAM2 (`cobgs export-onnx sam2 ...`)", "gdino": "Grounding DINO (`cobgs export-onnx gdino ...`)"}
            raise ValueError(f"masks.models_dir {params.models_dir}: its manifest.json has no "
                             f"{' and no '.join(names[n] for n in lacking)}, which masks.source {self.name!r} needs")

    def masks(self, req: MaskRequest) -> tuple[dict, dict]:
        """``({view name: uint8 [H, W] 0/255 at the view's size}, what was done)``."""
        raise NotImplementedError

    def empty_hint(self, req: MaskRequest, info: dict) -> str:
        """What to say when no view got a non-empty mask."""
        return ""


class FileMasks(MaskSource):
    name, reads, reads_folders = "files", ("files_threshold", "files_root"), True

    def route(self, from_folder):
        return "released masks (files)" if from_folder else "dataset masks"

    def masks(self, req):
        info: dict = {}
        if req.mask_dir is not None:
            masks, info["files"] = folder_masks(req.views, Path(req.mask_dir), req.params.files_threshold)
        else:
            masks = dataset_masks(req.views, req.object)
        return masks, info

    def empty_hint(self, req, info):
        if req.mask_dir is not None:
            return ""
        return (f" (the dataset's mask files of {req.object!r} are read as 8-bit images whose foreground is "
                ">= 128: masks holding 0/1 read as empty; save them as 0/255, or give the object a mask_dir, "
                "where any non-zero pixel counts)")


class NoisyMasks(FileMasks):
    name, reads = "noisy", ("files_threshold", "files_root", "noise")

    def route(self, from_folder):
        return ("released masks" if from_folder else "dataset masks") + " + noise"

    def masks(self, req):
        from cobgs.data.mask_noise import apply_mask_noise, mask_rng

        masks, info = super().masks(req)
        noise = req.params.noise
        records = {}
        for name in list(masks):
            masks[name], records[name] = apply_mask_noise(masks[name], noise, mask_rng(noise, f"{req.object}/{name}"))
        info["noise"] = {"params": noise, "records": records}
        return masks, info


class _Generated(MaskSource):
    """A route that prompts SAM2 (through the ONNX exports) and propagates."""

    models = ("sam2",)

    def masks(self, req):
        from cobgs.masks.manifest import load_manifest
        from cobgs.masks.session import SessionOptions

        if req.params.models_dir is None:  # params built without their checks (a library caller)
            raise InputError(MODELS_HELP.format(source=self.name))
        load_manifest(req.params.models_dir)  # fails here, naming the folder, before any image is read
        providers = (["CUDAExecutionProvider", "CPUExecutionProvider"] if req.device.startswith("cuda")
                     else ["CPUExecutionProvider"])
        options = SessionOptions(providers=providers, intra_op_threads=req.params.intra_op_threads)
        if any(v.path is None for v in req.views):
            raise InputError("the training views have no image files to prompt SAM2 with")
        info: dict = {}
        res = self._generate(req, options, info)
        import json

        info["generator"] = json.loads(Path(res.log_path).read_text(encoding="utf-8"))
        out = {}
        for v in req.views:  # the generator writes each image's own size; the training size may be smaller
            f = res.out_dir / f"{v.name}.png"
            if f.is_file():
                out[v.name] = _mask_at(f, v.width, v.height)
        return out, info

    def _generate(self, req, options, info):
        raise NotImplementedError


class TextMasks(_Generated):
    name, reads, version, models = "onnx", ("models_dir", "two_stage", "intra_op_threads"), 2, ("sam2", "gdino")
    # version 2: the authors' two-stage flow (stage-2 corrections, first-object emptiness, query order)

    def route(self, from_folder):
        return "text -> two-stage (Grounding DINO + SAM2)"

    def _generate(self, req, options, info):
        from cobgs.masks.api import generate_masks

        prompt = req.prompt or req.object.replace("_", " ")
        info["prompt"] = prompt
        return generate_masks([v.path for v in req.views], prompt, req.params.models_dir, req.scratch / "generated",
                              config=req.params.two_stage, names=[v.name for v in req.views],
                              log_path=req.scratch / "generated.json", options=options)


class ScribbleMasks(_Generated):
    name, reads = "nvos", ("models_dir", "scribbles", "intra_op_threads")

    def route(self, from_folder):
        return "scribbles -> SAM2"

    def _generate(self, req, options, info):
        from cobgs.masks.api import generate_masks_from_scribbles

        task = _nvos_task(req)
        names = [v.name for v in req.views]
        if task["reference"] not in names:
            raise InputError(f"NVOS reference view {task['reference']!r} is not a training view")
        return generate_masks_from_scribbles(
            [v.path for v in req.views], names.index(task["reference"]), task["positive_scribbles"],
            task["negative_scribbles"], req.params.models_dir, req.scratch / "generated", config=req.params.scribbles,
            names=names, log_path=req.scratch / "generated.json", options=options)


class ClickMasks(_Generated):
    name, reads = "points", ("models_dir", "points_file", "intra_op_threads")

    def route(self, from_folder):
        return "clicks -> SAM2"

    def check(self, params):
        if params.points_file is None:
            raise ValueError("masks.source 'points' needs masks.points_file = a JSON click file "
                             "(SAGA-v2's NVOS input points, or {\"objects\": {OBJECT: {\"frames\": "
                             "{VIEW: {\"positive\": [[x, y]], \"negative\": [[x, y]]}}}}}: docs/data_formats.md)")
        from cobgs.masks.clicks import read_clicks

        read_clicks(params.points_file)  # every value checked now, naming file, object and frame
        super().check(params)

    def _generate(self, req, options, info):
        from cobgs.masks.api import generate_masks_from_clicks

        prompts, info["clicks"] = click_prompts(req)
        return generate_masks_from_clicks([v.path for v in req.views], prompts, req.params.models_dir,
                                          req.scratch / "generated", names=[v.name for v in req.views],
                                          log_path=req.scratch / "generated.json", options=options,
                                          extra_log={"clicks": info["clicks"]})

    def empty_hint(self, req, info):
        if not info.get("clicks"):
            return ""
        landed = "; ".join(f"{f['frame']} ({f['image']}, {f['image_size'][0]}x{f['image_size'][1]} px): "
                           f"{f['positive']} positive at {f['points_px'][:3]}" for f in info["clicks"]["frames"][:4])
        return (f"; the clicks landed at {landed} (image pixels, x right, y down; see masks.json beside the log): "
                "are they on the object, in the frame image_size names?")


class PromptMaskClicks(_Generated):
    """SPIn-NeRF's prompt: the peers hand the prompt view's GT mask to their 3D method (SA3D
    ``load_spin_data``'s ``ref_id``, LUDVIG's reference "scribble"); a user has clicks. This
    route places ``masks.prompt_clicks`` positive clicks inside that mask
    (:func:`cobgs.masks.clicks.interior_clicks`: deterministic, no seed) and lets SAM2 segment
    the prompt view and propagate, as the ``points`` route does with a click file."""

    name, reads = "prompt_clicks", ("models_dir", "prompt_clicks", "intra_op_threads")

    def route(self, from_folder):
        return "clicks in the prompt view's mask -> SAM2"

    def _generate(self, req, options, info):
        import numpy as np

        from cobgs.data.nvos import read_gt_mask
        from cobgs.masks.api import FramePrompt, generate_masks_from_clicks
        from cobgs.masks.clicks import interior_clicks
        from cobgs.masks.images import image_size

        spin = req.spec.get("spin")
        if not spin:
            raise InputError(f"masks.source 'prompt_clicks' places clicks in a SPIn-NeRF scene's prompt-view mask; "
                             f"scene {req.spec['scene']!r} is of kind {req.spec['kind']!r} (use 'points' with a "
                             "click file)")
        names = [v.name for v in req.views]
        if spin["prompt"] not in names:
            raise InputError(f"SPIn-NeRF prompt view {spin['prompt']!r} is not a training view")
        i = names.index(spin["prompt"])
        ih, iw = image_size(req.views[i].path)
        gt = read_gt_mask(spin["masks"][spin["prompt"]])
        gt = (gt > (127 if gt.max(initial=0) > 1 else 0)).astype(np.uint8) * 255
        if gt.shape != (ih, iw):  # (the clicks are in the pixels of the image SAM2 reads)
            import cv2

            gt = cv2.resize(gt, (iw, ih), interpolation=cv2.INTER_NEAREST)
        pts = interior_clicks(gt > 127, req.params.prompt_clicks)
        info["clicks"] = {"frames": [{"frame": spin["prompt"], "image": Path(req.views[i].path).name,
                                      "positive": int(len(pts)), "negative": 0, "image_size": [iw, ih],
                                      "points_px": pts.round(2).tolist(), "from": spin["masks"][spin["prompt"]]}]}
        prompts = [FramePrompt(i, pts.astype(np.float32), np.ones(len(pts), np.float32))]
        return generate_masks_from_clicks([v.path for v in req.views], prompts, req.params.models_dir,
                                          req.scratch / "generated", names=names,
                                          log_path=req.scratch / "generated.json", options=options,
                                          extra_log={"clicks": info["clicks"]})


#: Every route, by name (``masks.source``).
SOURCES: dict[str, MaskSource] = {s.name: s for s in (FileMasks(), NoisyMasks(), TextMasks(), ScribbleMasks(),
                                                        ClickMasks(), PromptMaskClicks())}


def source_for(name: str) -> MaskSource:
    """The route called ``name``.

    Raises:
        InputError: no such route (the known ones named).
    """
    if name not in SOURCES:
        raise InputError(f"unknown mask source {name!r} (expected one of {list(SOURCES)})")
    return SOURCES[name]


# -- the routes' work ------------------------------------------------------------------------------
def _mask_at(path: Path, width: int, height: int):
    """A 0/255 mask file at ``width`` x ``height`` (area-resized, >= 0.5), uint8 0/255; pixels as
    stored (the EXIF orientation tag ignored, as every reader here)."""
    import cv2
    import numpy as np

    arr = cv2.imread(os.fspath(path), cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION)
    if arr is None:
        raise DataError("missing or unreadable mask PNG", path)
    m = (arr >= 128).astype(np.float32)
    if m.shape != (height, width):
        m = cv2.resize(m, (width, height), interpolation=cv2.INTER_AREA)
    return (m >= 0.5).astype(np.uint8) * 255


def _nvos_task(req: MaskRequest) -> dict:
    if req.spec.protocol != "nvos":
        raise InputError(f"masks.source {req.params.source!r} needs an NVOS scene (kind 'nvos'), got kind "
                         f"{req.spec.get('kind')!r}")
    task = req.spec.nvos_task(req.item, req.object)
    if task is None:
        raise InputError(f"NVOS scene {req.spec.scene!r} holds the tasks {sorted(req.spec.nvos_tasks)}; object "
                         f"{req.item!r} / {req.object!r} is none of them (name the object after its task)")
    return task


def object_mask_folder(root: Path, name: str) -> Path:
    """The folder of per-view masks of object ``name`` under ``masks.files_root``:
    ``<root>/<name>/``, or COB-GS's own output layout (``output/<scene>/masks/<task>/``
    given as ``output/``, or ``<scene>/masks/<task>/`` given as ``<scene>/``): the
    ``masks/<name>/`` folders one level down, when exactly one exists.

    Raises:
        InputError: none, or more than one, naming what is there.
    """
    if (root / name / "masks" / name).is_dir():  # output/fern/masks/fern: scene and task share the name
        return root / name / "masks" / name
    if (root / name).is_dir():
        return root / name
    found = [d for d in (root / "masks" / name, *sorted(root.glob(f"*/masks/{name}"))) if d.is_dir()]
    if len(found) == 1:
        return found[0]
    if len(found) > 1:
        raise InputError(f"masks.files_root {root}: object {name!r} has more than one mask folder "
                         f"({[str(d.relative_to(root)) for d in found]}); give the object a mask_dir")
    have = sorted(d.name for d in root.iterdir() if d.is_dir())[:8]
    raise InputError(f"masks.files_root {root}: no folder {name}/ for object {name!r}, nor "
                     f"<scene>/masks/{name}/ as COB-GS writes its output (folders there: {have}); "
                     f"name it after the object, or give the object a mask_dir")


def folder_masks(views, folder: Path, threshold: int) -> tuple[dict, dict]:
    """Per-view masks from a folder of images named after the views (uint8 0/255 at the
    training size) and what was read: files, original sizes, resizing, unused files.

    Raises:
        InputError / DataError: two masks for a view, an unreadable file, a mask of another
            aspect ratio, an EXIF-rotated mask, no mask named after a view.
    """
    import numpy as np
    from PIL import Image

    from cobgs.data.images import check_upright, same_aspect
    from cobgs.evaluate.protocols import resize_nearest

    by_stem: dict = {}
    for f in sorted(folder.iterdir()):
        if f.is_file() and f.suffix.lower() in MASK_SUFFIXES:
            by_stem.setdefault(f.stem, []).append(f)
    out, sizes, resized = {}, {}, []
    for v in views:
        files = by_stem.get(v.name, [])
        if len(files) > 1:
            raise InputError(f"mask_dir {folder}: more than one mask for view {v.name!r}: {[f.name for f in files]}")
        if not files:
            continue
        f = files[0]
        try:
            with Image.open(f) as im:
                a = np.asarray(im.convert("RGB"))
        except (OSError, ValueError, Image.DecompressionBombError) as exc:  # (a bomb: > 179 Mpx)
            raise DataError(f"cannot read it as an image ({exc})", f) from exc
        check_upright([f], "mask file")  # a rotated mask of an upright photo
        m = (a > threshold).any(axis=-1).astype(np.uint8) * 255
        sizes[v.name] = [int(m.shape[1]), int(m.shape[0])]
        if not same_aspect(m.shape[1], m.shape[0], v.width, v.height):
            raise InputError(f"mask file {f}: {m.shape[1]}x{m.shape[0]} px, but view {v.name!r} is "
                             f"{v.width}x{v.height}: another aspect ratio (transposed, cropped or another "
                             "view's?); masks are resized to the view only when the aspect matches")
        if m.shape != (v.height, v.width):  # NEAREST, as the evaluation scripts resize
            resized.append(v.name)
        out[v.name] = resize_nearest(m, v.height, v.width)
    if not out:
        raise InputError(f"mask_dir {folder}: no mask named after a training view (views like "
                         f"{[v.name for v in views[:3]]}; files like {sorted(by_stem)[:3]})")
    info = {"dir": str(folder), "threshold": threshold, "files": {n: by_stem[n][0].name for n in out},
            "source_size": sizes, "resized_nearest": sorted(resized),
            "training_size": [views[0].width, views[0].height],
            "unused_files": sorted(set(by_stem) - set(out))}
    return out, info


def dataset_masks(views, obj: str) -> dict:
    """The dataset's mask of ``obj`` per training view (uint8 0/255).

    Raises:
        InputError: the dataset has no mask of ``obj`` (naming the objects it has).
    """
    import numpy as np

    out = {}
    for v in views:
        m = v.masks.get(obj)
        if m is not None:
            out[v.name] = (m.cpu().numpy().astype(np.uint8) * 255)
    if not out:
        have = sorted({k for v in views for k in v.masks})
        raise InputError(f"masks.source 'files': the dataset has no masks of object {obj!r} on its training views "
                         f"(objects with masks: {have}); set the object's `mask` attribute, or use source 'onnx' / "
                         "'nvos'")
    return out


def click_prompts(req: MaskRequest) -> tuple[list, dict]:
    """The SAM2 prompts of this object from ``masks.points_file``, in each view image's own
    pixels, and what was used (for masks.json)."""
    import numpy as np

    from cobgs.masks.api import FramePrompt
    from cobgs.masks.clicks import SAGA, check_frame_size, locate, match_frames, read_clicks, to_image_pixels
    from cobgs.masks.images import image_size

    views, spec = req.views, req.spec
    clicks = read_clicks(req.params.points_file)
    nvos = _nvos_task(req) if spec.protocol == "nvos" else None
    entry = clicks.lookup([*req.click_names[:2], *([nvos["task"]] if nvos else []), *req.click_names[2:]]
                          if nvos else list(req.click_names))
    prompts, used = [], []
    if entry.layout == SAGA:
        if nvos is None:
            raise InputError(f"{locate(clicks, entry)}: SAGA-v2 clicks belong on an NVOS task's reference view, "
                             f"but scene {spec['scene']!r} is not an NVOS scene (kind 'nvos'); "
                             "use the per-object layout (docs/data_formats.md)")
        names = [v.name for v in views]
        if nvos["reference"] not in names:
            raise InputError(f"{locate(clicks, entry)}: NVOS reference view {nvos['reference']!r} is not a "
                             "training view")
        # The clicks are in the reference image's full resolution: its size from the
        # labels' copy, else the GT mask's (the same camera at full size).
        full_src = nvos.get("reference_image") or nvos["gt_mask"]
        fh, fw = image_size(full_src)
        frames = [(entry.frames[0], names.index(nvos["reference"]), (fw, fh))]
    else:
        idx = match_frames(clicks, entry, [(v.name, Path(v.path).name) for v in views],
                           [(v, "") for v in spec.test_views or []])
        frames = [(fc, i, entry.image_size) for fc, i in zip(entry.frames, idx)]
    for fc, i, frame_size in frames:
        frame = views[i].name if entry.layout == SAGA else fc.frame
        ih, iw = image_size(views[i].path)
        check_frame_size(clicks, entry, frame, frame_size, (iw, ih), views[i].path)
        pts = to_image_pixels(fc.points, frame_size, (iw, ih))
        outside = [pt for pt in pts.tolist() if not (0 <= pt[0] < iw and 0 <= pt[1] < ih)]
        if outside:
            raise InputError(f"{locate(clicks, entry, frame)}: click {[round(c, 1) for c in outside[0]]} lies "
                             f"outside the image ({iw}x{ih} px, {views[i].path}); clicks are in "
                             + ("the reference image's full resolution" if entry.layout == SAGA else
                                f"the pixels of {'image_size ' + str(list(frame_size)) if frame_size else 'the view image'}"))
        prompts.append(FramePrompt(i, pts.astype(np.float32), fc.labels.astype(np.float32)))
        used.append({"frame": views[i].name, "image": Path(views[i].path).name,
                     "positive": int((fc.labels == 1).sum()), "negative": int((fc.labels == 0).sum()),
                     "from_size": list(frame_size) if frame_size else None, "image_size": [iw, ih],
                     "points_px": pts.round(2).tolist()})
    return prompts, {"file": os.fspath(req.params.points_file), "layout": entry.layout, "entry": entry.key,
                     "scale": clicks.scale, "frames": used}


__all__ = ["MaskRequest", "MaskSource", "SOURCES", "source_for", "object_mask_folder", "folder_masks", "dataset_masks",
           "click_prompts", "MASK_SUFFIXES"]
