"""Stage ``masks``: one object's 2D masks on the training views, per scene x object.

Sources (``masks.source``):
  files  the dataset's own masks (``masks/<object>/`` folders, Blender alpha), training
         views only — held-out masks stay ground truth; or, when the object sets
         ``mask_dir``, a folder of per-view mask images named after the views (COB-GS's
         released NVOS masks: ``<IMG>.JPG``), any resolution (resized NEAREST to the
         training size), binarised ``> masks.files_threshold`` (0, as the released code);
         ``masks.files_root`` gives every object without a ``mask_dir`` the folder
         ``<files_root>/<object>`` (the object axis value's name);
  noisy  the same, corrupted by :mod:`cobgs.data.mask_noise` (robustness runs);
  onnx   two-stage text prompting, Grounding DINO + SAM2 (:func:`cobgs.masks.generate_masks`),
         prompt = the object's ``prompt`` attribute (default: its name, ``_`` as spaces);
  nvos   NVOS scribbles on the reference view -> SAM2 -> propagation
         (:func:`cobgs.masks.generate_masks_from_scribbles`);
  points clicks from ``masks.points_file`` -> SAM2 on each prompted frame -> propagation
         (:func:`cobgs.masks.generate_masks_from_clicks`): SAGA-v2's NVOS click file
         (positive clicks on the NVOS reference view, the route of COB-GS's released
         NVOS masks) or the per-object layout of :mod:`cobgs.masks.clicks`.
``onnx``, ``nvos`` and ``points`` need ``masks.models_dir`` (the folder ``cobgs export-onnx``
writes).

Output ``masks``: ``<view>.png`` (0/255 at the training size) for every training view
with a mask, and ``masks.json`` (source, per-view foreground area, empty views, the noise
records or the generator's log).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar, Optional

from cobgs.configs import Files, MaskNoiseParams, ScribbleConfig, TwoStageConfig, check_params
from pipeline import Resources, Stage

from ._common import StageInputError, load_scene, nvos_task, object_name, read_json, read_spec, write_json, write_png

SOURCES = ("files", "noisy", "onnx", "nvos", "points")


@dataclass(frozen=True)
class ObjectAttrs:
    """Attributes of an ``object`` axis value (objects are nested in scenes).

    Attributes:
        mask: the dataset object it segments (mask folder name, ``object`` for Blender
            alpha, the prompt for LERF-mask); default: the value's own name. Two values
            may name the same object, e.g. ``ball`` and ``ball_noisy`` with another
            ``masks.source``.
        prompt: text prompt for ``masks.source = "onnx"`` (default: the object name with
            ``_`` read as a space).
        mask_dir: ``masks.source = "files"`` reads this folder's per-view mask images
            (``<view>.<any image suffix>``, e.g. COB-GS's released ``IMG_4026.JPG``) instead
            of the dataset's masks; relative paths resolve against the workflow file.
    """

    mask: str = ""
    prompt: str = ""
    mask_dir: Optional[Path] = None

    def __post_init__(self) -> None:
        if self.mask_dir is not None and not Path(self.mask_dir).is_dir():
            raise ValueError(f"mask_dir {self.mask_dir} does not exist (a folder of per-view "
                             f"mask images named after the views, e.g. IMG_4026.JPG)")


@dataclass(frozen=True)
class MasksParams:
    """Attributes:
        source: one of :data:`SOURCES`.
        models_dir: ONNX model folder (``onnx`` / ``nvos``).
        noise: mask-noise parameters (``noisy``).
        two_stage: Alg. 1 thresholds (``onnx``).
        scribbles: scribble point sampling (``nvos``).
        intra_op_threads: onnxruntime threads per graph (0 = its choice).
        files_threshold: ``files`` from an object's ``mask_dir``: a mask pixel has some
            channel above this (0 = any non-zero, as COB-GS's released code reads its masks).
        files_root: ``files``: a folder holding one folder of per-view masks per object,
            named after the object value (e.g. COB-GS's released NVOS masks as
            ``fern/IMG_4026.JPG``, ``horns_center/...``); read like an object's ``mask_dir``,
            which wins where both are given. COB-GS's own output layout
            (``<scene>/masks/<task>/`` under ``output/``) is read as it is: a folder whose
            object folders sit one level down, in ``<anything>/masks/``, is found.
        points_file: ``points``: the click file (:mod:`cobgs.masks.clicks`): SAGA-v2's
            NVOS input points or the per-object layout. Checked when the workflow loads.
    """

    source: str = "files"
    models_dir: Optional[Path] = None
    noise: MaskNoiseParams = field(default_factory=MaskNoiseParams)
    two_stage: TwoStageConfig = field(default_factory=TwoStageConfig)
    scribbles: ScribbleConfig = field(default_factory=ScribbleConfig)
    intra_op_threads: int = 0
    files_threshold: int = 0
    files_root: Optional[Path] = None
    points_file: Optional[Path] = None

    RANGES: ClassVar[dict] = {"intra_op_threads": "[0, 1024]", "files_threshold": "[0, 254]"}
    CHOICES: ClassVar[dict] = {"source": SOURCES}

    def __post_init__(self) -> None:
        check_params(self)
        if self.files_root is not None and not Path(self.files_root).is_dir():
            raise ValueError(f"masks.files_root {self.files_root} does not exist (a folder with one "
                             f"folder of mask images per object, named after the object)")
        # Checked when the workflow is planned, before any task runs (fail fast: the
        # masks stage comes after hours of training on a real scene).
        if self.source == "points":
            if self.points_file is None:
                raise ValueError("masks.source 'points' needs masks.points_file = a JSON click file "
                                 "(SAGA-v2's NVOS input points, or {\"objects\": {OBJECT: {\"frames\": "
                                 "{VIEW: {\"positive\": [[x, y]], \"negative\": [[x, y]]}}}}}: docs/data_formats.md)")
            from cobgs.masks.clicks import read_clicks

            read_clicks(self.points_file)  # every value checked now, naming file, object and frame
        if self.source in ("onnx", "nvos", "points"):
            if self.models_dir is None:
                raise ValueError(_MODELS_HELP.format(source=self.source))
            if not Path(self.models_dir).is_dir():
                raise ValueError(f"masks.models_dir {self.models_dir} does not exist "
                                 f"(source {self.source!r} needs the ONNX model folder)")
            _check_models(self.models_dir, self.source)


def _check_models(models_dir: Path, source: str) -> None:
    """The model folder's manifest.json, read and checked when the workflow loads (its files
    named, the models the source needs present): not after hours of SfM and training."""
    from cobgs.errors import ModelError
    from cobgs.masks.manifest import load_manifest

    try:
        manifest = load_manifest(models_dir)
    except ModelError as exc:
        raise ValueError(f"masks.models_dir: {exc}") from None
    need = {"onnx": ("sam2", "gdino"), "nvos": ("sam2",), "points": ("sam2",)}[source]
    lacking = [n for n in need if getattr(manifest, n) is None]
    if lacking:
        names = {"sam2": "SAM2 (`cobgs export-onnx sam2 ...`)", "gdino": "Grounding DINO (`cobgs export-onnx gdino ...`)"}
        raise ValueError(f"masks.models_dir {models_dir}: its manifest.json has no "
                         f"{' and no '.join(names[n] for n in lacking)}, which masks.source {source!r} needs")


_MODELS_HELP = ("masks.source {source!r} needs masks.models_dir, which is not set: export the models "
                "with `cobgs export-onnx sam2 ...` (and `gdino` for text prompts) and pass the folder "
                "with `--set masks.models_dir=DIR` or `models_dir = ...` under [params.masks]. "
                "To run without models, read masks from files: `--set masks.source=files` (with "
                "`--set masks.files_root=DIR` for a folder of per-object mask folders, such as COB-GS's "
                "released NVOS masks); or, once the models exist, click prompts with "
                "`--set masks.source=points --set masks.points_file=FILE`")


def _run(ctx, inputs):
    p: MasksParams = ctx.params
    spec = read_spec(inputs["dataset"])
    obj = object_name(ctx)
    scene = load_scene(inputs["dataset"], inputs["poses"])
    views = scene.train
    t0 = time.perf_counter()
    info: dict = {"source": p.source, "object": obj, "scene": spec.scene}
    attrs = ctx.item.attrs.get("object")
    mask_dir = getattr(attrs, "mask_dir", None) if attrs is not None else None
    if mask_dir is None and p.files_root is not None and p.source in ("files", "noisy"):
        mask_dir = object_mask_folder(Path(p.files_root), ctx.item["object"])
    info["route"] = mask_route(p.source, mask_dir is not None)
    if p.source in ("files", "noisy"):
        if mask_dir is not None:
            masks, info["files"] = _folder_masks(views, Path(mask_dir), p.files_threshold)
        else:
            masks = _dataset_masks(views, obj, spec)
        if p.source == "noisy":
            from cobgs.data.mask_noise import apply_mask_noise, mask_rng

            noise = p.noise
            records = {}
            for name in list(masks):
                m, rec = apply_mask_noise(masks[name], noise, mask_rng(noise, f"{obj}/{name}"))
                masks[name] = m
                records[name] = rec
            info["noise"] = {"params": noise, "records": records}
        for name, m in masks.items():
            write_png(ctx.out_dir / f"{name}.png", m)
    else:
        _generate(ctx, p, spec, obj, views, info)
    areas = {}
    for v in views:
        f = ctx.out_dir / f"{v.name}.png"
        if f.is_file():
            import cv2

            a = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION)
            areas[v.name] = int((a >= 128).sum())
    info.update(views=len(areas), train_views=len(views), area_px=areas,
                empty=sorted(k for k, a in areas.items() if a == 0),
                without_mask=sorted(v.name for v in views if v.name not in areas))
    write_json(ctx.out_dir / Files.MASKS, info)  # (kept in the failure record below)
    if not areas or all(a == 0 for a in areas.values()):
        hint = ""
        if p.source in ("files", "noisy") and mask_dir is None:
            hint = (f" (the dataset's mask files of {obj!r} are read as 8-bit images whose "
                    "foreground is >= 128: masks holding 0/1 read as empty; save them as 0/255, "
                    "or give the object a mask_dir, where any non-zero pixel counts)")
        if p.source == "points" and info.get("clicks"):
            landed = "; ".join(f"{f['frame']} ({f['image']}, {f['image_size'][0]}x{f['image_size'][1]} px): "
                               f"{f['positive']} positive at {f['points_px'][:3]}" for f in info["clicks"]["frames"][:4])
            hint = (f"; the clicks landed at {landed} (image pixels, x right, y down; see masks.json beside the "
                    "log): are they on the object, in the frame image_size names?")
        raise StageInputError(f"object {obj!r}: no training view got a non-empty mask "
                              f"(source {p.source!r}); nothing to segment{hint}")
    ctx.log.info("masks of %r (%s): %d views, %d empty", obj, p.source, len(areas), len(info["empty"]))
    ctx.note(source=p.source, object=obj, views=len(areas), empty=len(info["empty"]),
             seconds=round(time.perf_counter() - t0, 3))
    return {"masks": ctx.out_dir}


def object_mask_folder(root: Path, name: str) -> Path:
    """The folder of per-view masks of object ``name`` under ``masks.files_root``:
    ``<root>/<name>/``, or COB-GS's own output layout (``output/<scene>/masks/<task>/``
    given as ``output/``, or ``<scene>/masks/<task>/`` given as ``<scene>/``): the
    ``masks/<name>/`` folders one level down, when exactly one exists."""
    if (root / name / "masks" / name).is_dir():  # output/fern/masks/fern: scene and task share the name
        return root / name / "masks" / name
    if (root / name).is_dir():
        return root / name
    found = [d for d in (root / "masks" / name, *sorted(root.glob(f"*/masks/{name}"))) if d.is_dir()]
    if len(found) == 1:
        return found[0]
    if len(found) > 1:
        raise StageInputError(f"masks.files_root {root}: object {name!r} has more than one mask folder "
                              f"({[str(d.relative_to(root)) for d in found]}); give the object a mask_dir")
    have = sorted(d.name for d in root.iterdir() if d.is_dir())[:8]
    raise StageInputError(f"masks.files_root {root}: no folder {name}/ for object {name!r}, nor "
                          f"<scene>/masks/{name}/ as COB-GS writes its output (folders there: {have}); "
                          f"name it after the object, or give the object a mask_dir")


def mask_route(source: str, from_folder: bool) -> str:
    """How the masks were made, in the words reports use."""
    if source == "files":
        return "released masks (files)" if from_folder else "dataset masks"
    if source == "noisy":
        return ("released masks" if from_folder else "dataset masks") + " + noise"
    if source == "onnx":
        return "text -> two-stage (Grounding DINO + SAM2)"
    if source == "points":
        return "clicks -> SAM2"
    return "scribbles -> SAM2"


_MASK_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff")


def _folder_masks(views, folder: Path, threshold: int) -> tuple[dict, dict]:
    """Per-view masks from a folder of images named after the views (uint8 0/255 at the
    training size) and what was read: files, original sizes, resizing, unused files."""
    import numpy as np
    from PIL import Image

    from cobgs.data.images import check_upright, same_aspect
    from cobgs.evaluate.protocols import resize_nearest

    by_stem: dict = {}
    for f in sorted(folder.iterdir()):
        if f.is_file() and f.suffix.lower() in _MASK_SUFFIXES:
            by_stem.setdefault(f.stem, []).append(f)
    out, sizes, resized = {}, {}, []
    for v in views:
        files = by_stem.get(v.name, [])
        if len(files) > 1:
            raise StageInputError(f"mask_dir {folder}: more than one mask for view {v.name!r}: "
                                  f"{[f.name for f in files]}")
        if not files:
            continue
        f = files[0]
        try:
            with Image.open(f) as im:
                a = np.asarray(im.convert("RGB"))
        except (OSError, ValueError, Image.DecompressionBombError) as exc:  # (a bomb: > 179 Mpx)
            raise StageInputError(f"mask file {f}: cannot read it as an image ({exc})") from exc
        check_upright([f], "mask file")  # a rotated mask of an upright photo
        m = (a > threshold).any(axis=-1).astype(np.uint8) * 255
        sizes[v.name] = [int(m.shape[1]), int(m.shape[0])]
        if not same_aspect(m.shape[1], m.shape[0], v.width, v.height):
            raise StageInputError(f"mask file {f}: {m.shape[1]}x{m.shape[0]} px, but view {v.name!r} is "
                                  f"{v.width}x{v.height}: another aspect ratio (transposed, cropped or another "
                                  "view's?); masks are resized to the view only when the aspect matches")
        if m.shape != (v.height, v.width):  # NEAREST, as the evaluation scripts resize
            resized.append(v.name)
        out[v.name] = resize_nearest(m, v.height, v.width)
    if not out:
        raise StageInputError(f"mask_dir {folder}: no mask named after a training view (views like "
                              f"{[v.name for v in views[:3]]}; files like {sorted(by_stem)[:3]})")
    info = {"dir": str(folder), "threshold": threshold, "files": {n: by_stem[n][0].name for n in out},
            "source_size": sizes, "resized_nearest": sorted(resized),
            "training_size": [views[0].width, views[0].height],
            "unused_files": sorted(set(by_stem) - set(out))}
    return out, info


def _dataset_masks(views, obj: str, spec: dict) -> dict:
    """The dataset's mask of ``obj`` per training view (uint8 0/255)."""
    import numpy as np

    out = {}
    for v in views:
        m = v.masks.get(obj)
        if m is not None:
            out[v.name] = (m.cpu().numpy().astype(np.uint8) * 255)
    if not out:
        have = sorted({k for v in views for k in v.masks})
        raise StageInputError(f"masks.source 'files': the dataset has no masks of object {obj!r} on its "
                              f"training views (objects with masks: {have}); set the object's `mask` "
                              "attribute, or use source 'onnx' / 'nvos'")
    return out


def _need_models(p: MasksParams) -> Path:
    if p.models_dir is None:  # params built without their checks (a caller of run())
        raise StageInputError(_MODELS_HELP.format(source=p.source))
    return p.models_dir


def _generate(ctx, p: MasksParams, spec: dict, obj: str, views, info: dict) -> None:
    from cobgs.masks.api import generate_masks, generate_masks_from_scribbles
    from cobgs.masks.manifest import load_manifest
    from cobgs.masks.session import SessionOptions

    models = _need_models(p)
    load_manifest(models)  # fails here, naming the folder, before any image is read
    providers = ["CUDAExecutionProvider", "CPUExecutionProvider"] if ctx.device.startswith("cuda") \
        else ["CPUExecutionProvider"]
    options = SessionOptions(providers=providers, intra_op_threads=p.intra_op_threads)
    paths = [v.path for v in views]
    if any(pth is None for pth in paths):
        raise StageInputError("the training views have no image files to prompt SAM2 with")
    out = ctx.scratch_dir / "generated"
    names = [v.name for v in views]
    if p.source == "onnx":
        attrs = ctx.item.attrs.get("object")
        prompt = (getattr(attrs, "prompt", "") if attrs is not None else "") or obj.replace("_", " ")
        res = generate_masks(paths, prompt, models, out, config=p.two_stage, names=names,
                             log_path=ctx.scratch_dir / "generated.json", options=options)
        info["prompt"] = prompt
    elif p.source == "points":
        from cobgs.masks.api import generate_masks_from_clicks

        prompts, info["clicks"] = _click_prompts(ctx, p, spec, obj, views)
        res = generate_masks_from_clicks(paths, prompts, models, out, names=names,
                                         log_path=ctx.scratch_dir / "generated.json", options=options,
                                         extra_log={"clicks": info["clicks"]})
    else:
        if spec.protocol != "nvos":
            raise StageInputError(f"masks.source 'nvos' needs an NVOS scene (kind 'nvos'), got kind "
                                  f"{spec.get('kind')!r}")
        task = nvos_task(spec, ctx.item["object"], obj)
        if task["reference"] not in names:
            raise StageInputError(f"NVOS reference view {task['reference']!r} is not a training view")
        res = generate_masks_from_scribbles(
            paths, names.index(task["reference"]), task["positive_scribbles"], task["negative_scribbles"],
            models, out, config=p.scribbles, names=names,
            log_path=ctx.scratch_dir / "generated.json", options=options)
    info["generator"] = read_json(res.log_path)
    # The generator writes each image's own size; the training size may be smaller.
    from ._common import read_mask_png

    for v in views:
        f = res.out_dir / f"{v.name}.png"
        if f.is_file():
            write_png(ctx.out_dir / f"{v.name}.png", read_mask_png(f, v.width, v.height).numpy())


def _click_names(item, obj: str, scene_task=None) -> list[str]:
    """The names a click file's entry of this object is looked up by: the object value, the
    dataset object it stands for, the scene's NVOS task(s), the scene."""
    attrs = item.attrs.get("scene")
    tasks = scene_task if scene_task is not None else getattr(attrs, "task", None) if attrs is not None else None
    tasks = [tasks] if isinstance(tasks, str) else list(tasks or [])
    return [item["object"], obj, *tasks, item["scene"]]


def _precheck(p: "MasksParams", item, inputs) -> None:
    """Click files, before the hours of SfM and training the masks task waits for: the
    object's entry when the run is planned, its frames and their sizes once the dataset
    task has listed the scene's views (Stage.precheck)."""
    if p.source in ("files", "noisy"):
        _precheck_mask_folder(p, item)
    if p.source != "points" or p.points_file is None:
        return
    from cobgs.masks.clicks import OWN, check_frame_size, locate, match_frames, read_clicks

    attrs = item.attrs.get("object")
    obj = (getattr(attrs, "mask", "") if attrs is not None else "") or item["object"]
    clicks = read_clicks(p.points_file)
    entry = clicks.lookup(_click_names(item, obj))
    if "dataset" not in inputs:
        return
    spec = read_spec(inputs["dataset"])
    if entry.layout != OWN:
        if spec.protocol != "nvos":
            raise ValueError(f"{locate(clicks, entry)}: SAGA-v2 clicks belong on an NVOS task's reference view, but "
                             f"scene {spec['scene']!r} is not an NVOS scene (kind 'nvos'); use the per-object layout "
                             "(docs/data_formats.md)")
        return  # (the NVOS reference view, checked when the masks task runs)
    from cobgs.data.images import probe

    files = _view_files(inputs["dataset"], spec)
    held = set(spec.test_views)
    train = [(v, files.get(v, "")) for v in spec.views if v not in held]
    idx = match_frames(clicks, entry, [(n, Path(f).name if f else "") for n, f in train],
                       [(v, Path(files[v]).name if v in files else "") for v in spec.views if v in held])
    for fc, i in zip(entry.frames, idx):
        name, f = train[i]
        if f and entry.image_size is not None:
            w, h, _ = probe(f)
            check_frame_size(clicks, entry, fc.frame, entry.image_size, (w, h), f)


def _precheck_mask_folder(p: "MasksParams", item) -> None:
    """An object's mask folder (``mask_dir``, or ``files_root/<object>``), when the run is
    planned: every file stored upright (no EXIF orientation tag, :mod:`cobgs.data.images`)."""
    attrs = item.attrs.get("object")
    folder = getattr(attrs, "mask_dir", None) if attrs is not None else None
    if folder is None and p.files_root is not None:
        try:
            folder = object_mask_folder(Path(p.files_root), item["object"])
        except StageInputError:
            return  # (named when the task runs)
    if folder is None or not Path(folder).is_dir():
        return
    from cobgs.data.images import check_upright
    from cobgs.errors import DataError

    try:
        check_upright(sorted(f for f in Path(folder).iterdir() if f.is_file() and f.suffix.lower() in _MASK_SUFFIXES),
                      "mask file")
    except DataError as exc:
        raise ValueError(str(exc)) from None


def _view_files(dataset_dir: Path, spec) -> dict:
    """view name -> its image file in the folder SfM reads, where the dataset names one."""
    from ._common import spec_path

    images = spec.images
    if not images:
        return {}
    folder = spec_path(dataset_dir, images.get("dir"))
    stems = {Path(n).stem: n for n in images.get("names") or []}
    return {v: folder / stems[v] for v in spec.views if v in stems}


def _click_prompts(ctx, p: MasksParams, spec: dict, obj: str, views) -> tuple[list, dict]:
    """The SAM2 prompts of this object from ``masks.points_file``, in each view image's own
    pixels, and what was used (for masks.json)."""
    import numpy as np

    from cobgs.masks.api import FramePrompt
    from cobgs.masks.clicks import SAGA, check_frame_size, locate, match_frames, read_clicks, to_image_pixels
    from cobgs.masks.images import image_size

    clicks = read_clicks(p.points_file)
    nvos = nvos_task(spec, ctx.item["object"], obj) if spec.protocol == "nvos" else None
    try:
        entry = clicks.lookup(_click_names(ctx.item, obj, [nvos["task"]] if nvos else None))
    except ValueError as exc:
        raise StageInputError(str(exc)) from exc
    prompts, used = [], []
    if entry.layout == SAGA:
        if nvos is None:
            raise StageInputError(f"{locate(clicks, entry)}: SAGA-v2 clicks belong on an NVOS task's reference view, "
                                  f"but scene {spec['scene']!r} is not an NVOS scene (kind 'nvos'); "
                                  "use the per-object layout (docs/data_formats.md)")
        names = [v.name for v in views]
        if nvos["reference"] not in names:
            raise StageInputError(f"{locate(clicks, entry)}: NVOS reference view {nvos['reference']!r} is not a "
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
        try:
            check_frame_size(clicks, entry, frame, frame_size, (iw, ih), views[i].path)
        except ValueError as exc:
            raise StageInputError(str(exc)) from None
        pts = to_image_pixels(fc.points, frame_size, (iw, ih))
        outside = [pt for pt in pts.tolist() if not (0 <= pt[0] < iw and 0 <= pt[1] < ih)]
        if outside:
            raise StageInputError(f"{locate(clicks, entry, frame)}: click {[round(c, 1) for c in outside[0]]} lies "
                                  f"outside the image ({iw}x{ih} px, {views[i].path}); clicks are in "
                                  + ("the reference image's full resolution" if entry.layout == SAGA else
                                     f"the pixels of {'image_size ' + str(list(frame_size)) if frame_size else 'the view image'}"))
        prompts.append(FramePrompt(i, pts.astype(np.float32), fc.labels.astype(np.float32)))
        used.append({"frame": views[i].name, "image": Path(views[i].path).name,
                     "positive": int((fc.labels == 1).sum()), "negative": int((fc.labels == 0).sum()),
                     "from_size": list(frame_size) if frame_size else None, "image_size": [iw, ih],
                     "points_px": pts.round(2).tolist()})
    return prompts, {"file": str(p.points_file), "layout": entry.layout, "entry": entry.key,
                     "scale": clicks.scale, "frames": used}


# What each source reads of the params: the cache key keeps only that, so tuning one
# route (the text route's thresholds, say) never recomputes another's masks.
_ROUTE_KEYS = {
    "files": ("files_threshold", "files_root"),
    "noisy": ("files_threshold", "files_root", "noise"),
    "onnx": ("models_dir", "two_stage", "intra_op_threads"),
    "nvos": ("models_dir", "scribbles", "intra_op_threads"),
    "points": ("models_dir", "points_file", "intra_op_threads"),
}
# Bumped when a route's behaviour changes (the stage version would recompute every route).
# onnx 2: the authors' two-stage flow (stage-2 corrections, first-object emptiness, query order).
_ROUTE_VERSIONS = {"onnx": 2}


def _key_params(params: "MasksParams", full: dict) -> dict:
    keys = _ROUTE_KEYS[params.source]
    out = {"source": params.source, **{k: full[k] for k in keys}}
    if params.source in _ROUTE_VERSIONS:
        out["route_version"] = _ROUTE_VERSIONS[params.source]
    return out


STAGE = Stage(
    name="masks", version=3, run=_run, inputs=("dataset", "poses"), outputs=("masks",), params=MasksParams,
    key_params=_key_params, precheck=_precheck, precheck_inputs=("dataset",),
    level=("scene", "object"), uses_device=True, resources=Resources(cpus=2),
    description="an object's training-view masks: dataset files, noisy copies, ONNX text, NVOS scribbles or clicks",
)

AXIS_SCHEMAS = {"object": ObjectAttrs}
