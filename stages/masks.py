"""Stage ``masks``: one object's 2D masks on the training views, per scene x object.

A thin adapter: the routes (``masks.source``: files, noisy, onnx, nvos, points) are the
classes of :mod:`cobgs.masks.sources`, one object each (the params it reads, its version, its
check, its run). This stage builds the route's :class:`~cobgs.masks.sources.MaskRequest` from
the task (the scene, the object's attributes), writes what the route returns and checks that
some view got a mask. ``onnx``, ``nvos`` and ``points`` need ``masks.models_dir`` (the folder
``cobgs export-onnx`` writes).

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
from cobgs.masks.sources import SOURCES as ROUTES  # (torch-free)
from pipeline import Resources, Stage

from ._common import StageInputError, load_scene, object_name, read_spec, write_json, write_png



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
        source: a route of :data:`cobgs.masks.sources.SOURCES` (files, noisy, onnx, nvos, points,
            prompt_clicks).
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
        prompt_clicks: ``prompt_clicks`` (SPIn-NeRF): positive clicks placed inside the prompt
            view's GT mask (the first at the point farthest from its edge, then spread).
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
    prompt_clicks: int = 3

    RANGES: ClassVar[dict] = {"intra_op_threads": "[0, 1024]", "files_threshold": "[0, 254]",
                              "prompt_clicks": "[1, 64]"}
    CHOICES: ClassVar[dict] = {"source": ROUTES}  # (the registry itself: a route added there is a choice)

    def __post_init__(self) -> None:
        check_params(self)
        if self.files_root is not None and not Path(self.files_root).is_dir():
            raise ValueError(f"masks.files_root {self.files_root} does not exist (a folder with one "
                             f"folder of mask images per object, named after the object)")
        # Checked when the workflow is planned, before any task runs (fail fast: the masks stage
        # comes after hours of training on a real scene): the route's own checks.
        ROUTES[self.source].check(self)


def _run(ctx, inputs):
    import cv2

    from cobgs.errors import DataError, InputError
    from cobgs.masks.sources import MaskRequest, object_mask_folder

    p: MasksParams = ctx.params
    route = ROUTES[p.source]  # (the one lookup)
    spec = read_spec(inputs["dataset"])
    obj = object_name(ctx)
    scene = load_scene(inputs["dataset"], inputs["poses"])
    views = scene.train
    t0 = time.perf_counter()
    attrs = ctx.item.attrs.get("object")
    mask_dir = getattr(attrs, "mask_dir", None) if attrs is not None else None
    try:
        if mask_dir is None and p.files_root is not None and route.reads_folders:
            mask_dir = object_mask_folder(Path(p.files_root), ctx.item["object"])
        req = MaskRequest(object=obj, item=ctx.item["object"], views=views, spec=spec, params=p, mask_dir=mask_dir,
                          prompt=getattr(attrs, "prompt", "") if attrs is not None else "",
                          click_names=tuple(_click_names(ctx.item, obj)), scratch=ctx.scratch_dir, device=ctx.device)
        masks, made = route.masks(req)
    except (InputError, DataError, ValueError) as exc:  # the request's own mistakes: one line, no traceback
        raise StageInputError(str(exc)) from exc
    info: dict = {"source": p.source, "object": obj, "scene": spec.scene, "route": route.route(mask_dir is not None),
                  **made}
    for name, m in masks.items():
        write_png(ctx.out_dir / f"{name}.png", m)
    areas = {}
    for v in views:
        f = ctx.out_dir / f"{v.name}.png"
        if f.is_file():
            a = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION)
            areas[v.name] = int((a >= 128).sum())
    info.update(views=len(areas), train_views=len(views), area_px=areas,
                empty=sorted(k for k, a in areas.items() if a == 0),
                without_mask=sorted(v.name for v in views if v.name not in areas))
    write_json(ctx.out_dir / Files.MASKS, info)  # (kept in the failure record below)
    if not areas or all(a == 0 for a in areas.values()):
        raise StageInputError(f"object {obj!r}: no training view got a non-empty mask "
                              f"(source {p.source!r}); nothing to segment{route.empty_hint(req, info)}")
    ctx.log.info("masks of %r (%s): %d views, %d empty", obj, p.source, len(areas), len(info["empty"]))
    ctx.note(source=p.source, object=obj, views=len(areas), empty=len(info["empty"]),
             seconds=round(time.perf_counter() - t0, 3))
    return {"masks": ctx.out_dir}


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
    from cobgs.data.images import check_upright
    from cobgs.errors import DataError, InputError
    from cobgs.masks.sources import MASK_SUFFIXES, object_mask_folder

    attrs = item.attrs.get("object")
    folder = getattr(attrs, "mask_dir", None) if attrs is not None else None
    if folder is None and p.files_root is not None:
        try:
            folder = object_mask_folder(Path(p.files_root), item["object"])
        except InputError:
            return  # (named when the task runs)
    if folder is None or not Path(folder).is_dir():
        return
    try:
        check_upright(sorted(f for f in Path(folder).iterdir() if f.is_file() and f.suffix.lower() in MASK_SUFFIXES),
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


def _key_params(params: "MasksParams", full: dict) -> dict:
    """What the route reads of the params (:meth:`cobgs.masks.sources.MaskSource.key_params`): tuning
    one route (the text route's thresholds, say) never recomputes another's masks."""
    return ROUTES[params.source].key_params(full)


STAGE = Stage(
    name="masks", version=3, run=_run, inputs=("dataset", "poses"), outputs=("masks",), params=MasksParams,
    key_params=_key_params, precheck=_precheck, precheck_inputs=("dataset",),
    level=("scene", "object"), uses_device=True, resources=Resources(cpus=2),
    description="an object's training-view masks: dataset files, noisy copies, ONNX text, NVOS scribbles or clicks",
)

AXIS_SCHEMAS = {"object": ObjectAttrs}
