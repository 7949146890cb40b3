"""Stage ``dataset``: generate a synthetic scene, or ingest an external one, per scene.

The scene's *kind* and location come from the ``scene`` axis attributes
(:class:`SceneAttrs`); how to ingest it from the params (:class:`DatasetParams`). The output
``dataset`` artifact holds ``dataset.json`` (see stages/_common.py) and, for synthetic
scenes, the generated scene itself. External data is only read: the spec points at it by
absolute path, so after editing such data in place rerun with ``--force dataset``.

Kinds:
  synthetic  cobgs.data.synthetic preset (exact masks; exact-GT protocol)
  transforms NeRF-style transforms.json with masks/<object>/ (exact-GT protocol when masks)
  blender    NeRF-synthetic (alpha = object mask "object"; exact-GT protocol)
  llff       poses_bounds.npy + images_<k>/ (no masks)
  colmap     a COLMAP model + images/ (masks/<object>/ optional)
  images     a folder of images without poses (SfM required)
  nvos       an LLFF scene + the NVOS labels folder (NVOS protocol; target view held out)
  lerf_mask  a LERF-mask scene (LERF-mask protocol; split from images_train/)
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar, Optional, Union

from cobgs.configs import Files, check_params
from pipeline import Resources, Stage

from ._common import SPEC_FORMAT, SPEC_VERSION, StageInputError, spec_path, write_json

KINDS = ("synthetic", "transforms", "blender", "llff", "colmap", "images", "nvos", "lerf_mask")
_POSED_FORMATS = {"transforms": "transforms", "blender": "blender", "llff": "llff", "colmap": "colmap",
                  "nvos": None, "lerf_mask": "colmap"}
_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


@dataclass(frozen=True)
class SceneAttrs:
    """Attributes of a ``scene`` axis value: what the data is and where it lives.

    Attributes:
        kind: one of :data:`KINDS`.
        path: the data folder (every kind but ``synthetic``); relative paths resolve
            against the workflow file; checked when the workflow loads (fail fast). For
            ``kind = "nvos"`` a missing ``<path>`` is also looked for as
            ``<path>_undistort`` (NeX's copies, as fvdb's ``scenes/fern_undistort``).
        labels: the NVOS labels folder (``kind = "nvos"``): the folder holding ``masks/``,
            ``reference_image/`` and ``scribbles/``, or the ``labels/`` the download
            unpacks (its ``llff/`` sub-folder is read).
        task: the NVOS task (default: the scene value's name), or a list of tasks on this
            scene (the two horns tasks share the scene, its target and its reference view):
            the scene is trained once and each task is an object of it (the object's name
            or ``mask`` is the task); every target is held out.
        scene_type: "forward" or "360" (default: from the kind / preset).
        trained: a scene trained elsewhere, used instead of training one: an output folder
            of the original 3DGS code (``point_cloud/iteration_<N>/point_cloud.ply``,
            ``cameras.json``, ``cfg_args``, optional ``chkpnt<N>.pth`` whose Adam state the
            texture stages continue) or any standard 3DGS PLY, trained on this scene's data
            (checked: :mod:`cobgs.data.trained3dgs`).
        trained_iteration: which saved iteration of a 3DGS output folder (0 = the highest).
    """

    kind: str = "synthetic"
    path: Optional[Path] = None
    labels: Optional[Path] = None
    task: Union[str, tuple[str, ...]] = ""
    scene_type: str = ""
    # read by the train stage only: its cache key (and the PLY's fingerprint) are the train
    # stage's, so touching the PLY does not rerun the dataset or SfM stages
    trained: Optional[Path] = field(default=None, metadata={"key_stages": ("train",)})
    trained_iteration: int = field(default=0, metadata={"key_stages": ("train",)})

    def __post_init__(self) -> None:
        if self.trained is not None:
            if not Path(self.trained).exists():
                raise ValueError(f"trained {self.trained} does not exist (a 3DGS output folder or a "
                                 f"PLY file)")
            from cobgs.data.trained_layout import check_trained

            try:  # the folder's layout, the PLY's header, cfg_args, cameras.json: before any task runs
                check_trained(Path(self.trained), self.trained_iteration)
            except Exception as exc:  # DataError names the file
                raise ValueError(f"trained: {exc}") from exc
        if self.trained_iteration < 0:
            raise ValueError(f"trained_iteration must be >= 0, got {self.trained_iteration}")
        if self.kind not in KINDS:
            raise ValueError(f"kind must be one of {list(KINDS)}, got {self.kind!r}")
        if not isinstance(self.task, str):
            if self.kind != "nvos" or not self.task:
                raise ValueError("a list of tasks (several NVOS tasks on one scene) needs kind 'nvos' and "
                                 "at least one task")
            if len(set(self.task)) != len(self.task):
                raise ValueError(f"task repeats a task: {list(self.task)}")
        if self.scene_type not in ("", "forward", "360"):
            raise ValueError(f"scene_type must be 'forward' or '360', got {self.scene_type!r}")
        if self.kind == "synthetic":
            return
        if self.path is None:
            raise ValueError(f"kind {self.kind!r} needs path = the data folder")
        if self.kind == "nvos" and not Path(self.path).is_dir():
            # NeX's copies (the ones the NVOS README and fvdb point to) are <scene>_undistort
            alt = Path(f"{os.fspath(self.path).rstrip('/')}_undistort")
            if alt.is_dir():
                object.__setattr__(self, "path", alt)
        if not Path(self.path).is_dir():
            raise ValueError(f"data folder {self.path} (kind {self.kind!r}) does not exist")
        if self.kind == "images" and not (Path(self.path) / "images").is_dir():
            loose = [f.name for f in Path(self.path).iterdir()
                     if f.suffix.lower() in (".jpg", ".jpeg", ".png")][:3]
            raise ValueError(f"path {self.path} has no images/ subfolder, where kind 'images' reads "
                             "the photos" + (f" (the folder holds images such as {loose}: move them "
                                             "into an images/ subfolder)" if loose else ""))
        if self.kind == "nvos":
            if self.labels is None:
                raise ValueError("kind 'nvos' needs labels = the NVOS labels folder "
                                 "(masks/, reference_image/, scribbles/)")
            if not Path(self.labels).is_dir():
                raise ValueError(f"NVOS labels folder {self.labels} does not exist")
            from cobgs.data.nvos import labels_root

            try:
                labels_root(self.labels)  # labels/ or labels/llff: either is read
            except Exception as exc:
                raise ValueError(str(exc)) from exc


@dataclass(frozen=True)
class DatasetParams:
    """How a scene is generated or ingested.

    Attributes:
        preset: synthetic preset ("demo", "forward", "orbit").
        seed: synthetic seed.
        width_px, height_px, num_views, supersampling: synthetic overrides (0 = preset's).
        workers: processes rendering synthetic views (the output does not depend on it).
        downscale: divide the image size for training (LLFF: picks ``images_<k>/``).
        images_dir: image sub-folder SfM runs on ("" = ``images_<downscale>/`` when it
            exists, else ``images/``); when given, ``downscale`` applies after SfM.
        view_stride: keep every k-th view (sorted by name) — subsets of long captures.
        max_views: keep at most this many views after the stride (0 = all).
        test_every: hold out every k-th kept view when the data defines no split.
        background: RGB in [0, 1] that RGBA images are composited on (None: the reader's).
    """

    preset: str = "demo"
    seed: int = 0
    width_px: int = 0
    height_px: int = 0
    num_views: int = 0
    supersampling: int = 0
    workers: int = 1
    downscale: float = 1.0
    images_dir: str = ""
    view_stride: int = 1
    max_views: int = 0
    test_every: int = 8
    background: Optional[tuple[float, float, float]] = None

    RANGES: ClassVar[dict] = {
        "seed": "[0, 2147483647]", "width_px": "[0, 16384]", "height_px": "[0, 16384]", "num_views": "[0, 10000]",
        "supersampling": "[0, 16]", "workers": "[0, 256]", "downscale": "(0, 64]", "view_stride": "[1, 1e6]",
        "max_views": "[0, 1e6]", "test_every": "[0, 1e6]", "background": "[0, 1]"}

    def __post_init__(self) -> None:
        check_params(self)
        if self.view_stride < 1 or self.max_views < 0 or self.test_every < 0:
            raise ValueError("view_stride must be >= 1, max_views and test_every >= 0")
        if self.test_every == 1:
            raise ValueError("test_every = 1 holds out every view, leaving nothing to train on: 0 holds out "
                             "none, k >= 2 every k-th view")
        if not self.downscale > 0:
            raise ValueError(f"downscale must be > 0, got {self.downscale}")


def _stems(folder: Path) -> list[str]:
    if not folder.is_dir():
        raise StageInputError(f"{folder}: image folder not found")
    return sorted(p.stem for p in folder.iterdir() if p.is_file() and p.suffix.lower() in _IMAGE_SUFFIXES)


def _names(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.is_file() and p.suffix.lower() in _IMAGE_SUFFIXES)


def _subset(names: list[str], p: DatasetParams) -> list[str]:
    out = names[:: p.view_stride]
    return out[: p.max_views] if p.max_views else out


def _every(names: list[str], k: int) -> list[str]:
    return [n for i, n in enumerate(names) if k and i % k == 0]


def _sfm_images(root: Path, p: DatasetParams) -> tuple[Path, float]:
    """(folder SfM reads, downscale applied to its images afterwards)."""
    if p.images_dir:
        d = root / p.images_dir
        if not d.is_dir():
            raise StageInputError(f"dataset.images_dir: {d} does not exist")
        return d, p.downscale
    k = int(round(p.downscale))
    if abs(p.downscale - k) < 1e-9 and k > 1 and (root / f"images_{k}").is_dir():
        return root / f"images_{k}", 1.0
    return root / "images", p.downscale


def _sfm_images_as_views(out_dir: Path, scene, sfm_dir: Path) -> Path:
    """The SfM image folder, as copies named after the views when the reader matched files
    named otherwise (nerf_llff_data's images_4/image000.png for IMG_4026): SfM names its
    images after the files, and the views, the NVOS task and the masks use the views'
    names. The copies live in the artifact (returned relative to it: the artifact moves
    when it is committed)."""
    import shutil

    views = [v for v in scene.views if v.path]
    if all(Path(v.path).stem == v.name for v in views):
        return sfm_dir
    out = out_dir / "sfm_images"
    out.mkdir(parents=True, exist_ok=True)
    for v in views:
        src = Path(v.path)
        if src.parent.resolve() != sfm_dir.resolve():
            src = sfm_dir / src.name  # the folder SfM reads holds the file under its own name
        shutil.copy2(src, out / f"{v.name}{src.suffix}")
    return Path(out.name)


def _run(ctx, inputs):
    """dataset.json for one scene: the fields every kind has, then its kind's builder's."""
    p: DatasetParams = ctx.params
    attrs: SceneAttrs = ctx.item.attrs["scene"]
    spec: dict = {"format": SPEC_FORMAT, "version": SPEC_VERSION, "scene": ctx.item["scene"], "kind": attrs.kind,
                  "protocol": "none", "objects": [], "sfm_downscale": 1.0}
    reader: dict = {"format": _POSED_FORMATS.get(attrs.kind), "path": None, "downscale": p.downscale,
                    "background": None if p.background is None else list(p.background)}
    if attrs.kind != "synthetic":
        root = Path(attrs.path).resolve()
        spec["source"] = os.fspath(root)
        reader["path"] = os.fspath(root)
    _BUILDERS.get(attrs.kind, _build_posed)(ctx, p, attrs, spec, reader)
    if spec.get("images") and attrs.kind != "synthetic":
        # one reading of "up" for SfM, masks and clicks: rotated photos are refused (cobgs.data.images)
        from cobgs.data.images import check_upright

        folder = spec_path(ctx.out_dir, spec["images"]["dir"])
        check_upright([folder / n for n in spec["images"]["names"]], "photo")
    spec["reader"] = reader
    write_json(ctx.out_dir / Files.DATASET, spec)
    ctx.log.info("dataset %s (%s): %d views, %d held out, objects %s, protocol %s", spec["scene"], attrs.kind,
                 len(spec["views"]), len(spec["test_views"]), spec["objects"], spec["protocol"])
    ctx.note(kind=attrs.kind, views=len(spec["views"]), test_views=len(spec["test_views"]),
             objects=spec["objects"], protocol=spec["protocol"], scene_type=spec["scene_type"])
    return {"dataset": ctx.out_dir}


def _check_blender_objects(ctx, root: Path, have: list) -> None:
    """A NeRF-synthetic scene's objects come from the images' alpha channel (``object``) or
    ``masks/<object>/`` folders; an object the workflow asks for that neither gives fails
    here, in the first task, naming the folder (objects with a text prompt are exempt)."""
    for it in ctx.items:
        if "object" not in it.axes:
            continue
        attrs = it.attrs.get("object")
        name = (getattr(attrs, "mask", "") or it["object"]) if attrs is not None else it["object"]
        if name in have or (attrs is not None and getattr(attrs, "prompt", "")) or \
                (attrs is not None and getattr(attrs, "mask_dir", None) is not None):
            continue
        why = ", ".join(w for w in ("its images have no alpha channel" if "object" not in have else "",
                                    f"it has masks of {have} only" if have else "") if w)
        raise StageInputError(f"object {it['object']!r} of scene {ctx.item['scene']!r}: {root} gives no "
                              f"mask of {name!r} ({why}, and there is no masks/{name}/ folder); add "
                              f"masks/{name}/<image>.png, or set the object's mask / prompt")




def _build_synthetic(ctx, p: DatasetParams, attrs: SceneAttrs, spec: dict, reader: dict) -> None:
    """A synthetic scene, generated into the artifact (exact GT, amodal masks)."""
    from cobgs.data.synthetic import generate_scene

    out = generate_scene(ctx.out_dir / "scene", p.preset, p.seed, progress=False,
                         width_px=p.width_px or None, height_px=p.height_px or None,
                         num_views=p.num_views or None, supersampling=p.supersampling or None,
                         workers=p.workers)
    from ._common import read_json

    meta = read_json(out / "scene.json")
    tf = read_json(out / "transforms.json")
    reader.update(format="transforms", path="scene")
    views = [Path(f["file_path"]).stem for f in tf["frames"]]
    test = [Path(f).stem for f in tf.get("test_filenames", [])]
    spec.update(protocol="exact", synthetic={k: meta[k] for k in ("preset", "seed", "trajectory",
                                                                    "image_size", "supersampling",
                                                                    "num_views")},
                objects=[o["name"] for o in meta["objects"] if o.get("target", True)],
                distractors=[o["name"] for o in meta["objects"] if not o.get("target", True)],
                scene_type=attrs.scene_type or ("360" if meta["trajectory"] == "orbit" else "forward"),
                images={"dir": "scene/images", "names": [Path(f["file_path"]).name for f in tf["frames"]]},
                has_poses=True,
                amodal={"source": "files", "dir": "scene/amodal",
                        "objects": [o["name"] for o in meta["objects"]]})
    kept = _subset(views, p)
    spec.update(views=kept, test_views=[v for v in test if v in set(kept)])


def _build_images(ctx, p: DatasetParams, attrs: SceneAttrs, spec: dict, reader: dict) -> None:
    """Photos without poses: SfM finds them."""
    root = Path(spec["source"])
    sfm_dir, post = _sfm_images(root, p)
    names = _subset(_names(sfm_dir), p)
    stems = [Path(n).stem for n in names]
    spec.update(views=stems, test_views=_every(stems, p.test_every), has_poses=False,
                images={"dir": os.fspath(sfm_dir), "names": names}, sfm_downscale=post,
                scene_type=attrs.scene_type or "360")


def _build_nvos(ctx, p: DatasetParams, attrs: SceneAttrs, spec: dict, reader: dict) -> None:
    """An LLFF scene and the NVOS labels: one or several tasks, their targets held out."""
    from cobgs.data.readers import read_scene

    root = Path(spec["source"])
    name = ctx.item["scene"]
    from cobgs.data.nvos import read_nvos_task

    names = (attrs.task or name,) if isinstance(attrs.task, str) else attrs.task
    tasks = [read_nvos_task(attrs.labels, t) for t in names]
    task = tasks[0]
    targets = sorted({t.target for t in tasks})
    for t in tasks:
        if t.reference in targets:
            raise StageInputError(f"NVOS task {t.task!r}: its reference view {t.reference!r} is "
                                  f"another task's held-out target; give those tasks their own scenes")
    fmt = _detect(root)
    # The NVOS GT is in the captured (distorted) frame at every size, and the
    # reference methods read nerf_llff_data's SIMPLE_RADIAL camera as a pinhole: the
    # images are read the same way at every downscale (undistorting the full-size
    # images would move them off the GT: 512x384 -> 510x382).
    reader.update(format=fmt, distortion="ignore")
    scene = read_scene(root, format=fmt, downscale=p.downscale, test_every=0, distortion="ignore")
    stems = sorted(v.name for v in scene.views)
    for t in tasks:
        for need in (t.target, t.reference):
            if need not in stems:
                raise StageInputError(f"NVOS task {t.task!r}: view {need!r} is not an image of "
                                      f"{root} (images: {stems[:3]} ...)")
    sfm_dir, post = _sfm_images(root, p)
    sfm_dir = _sfm_images_as_views(ctx.out_dir, scene, sfm_dir)
    spec["notes"] = list(scene.notes)
    if len(tasks) > 1:  # one training, shared by the scene's tasks
        spec["nvos_tasks"] = {t.task: t.to_json() for t in tasks}
    if any("read as a pinhole" in n for n in scene.notes):
        spec["notes"].append(
            f"NVOS at downscale {p.downscale:g}: images kept in the captured frame (camera read as "
            "a pinhole, not undistorted), the frame the NVOS ground truth is in")
    spec.update(protocol="nvos", nvos=task.to_json(), objects=[t.task for t in tasks],
                views=stems, test_views=targets, has_poses=True,
                images={"dir": os.fspath(sfm_dir),
                        "names": _names(sfm_dir if sfm_dir.is_absolute()
                                        else ctx.out_dir / sfm_dir)},
                sfm_downscale=post,
                scene_type=attrs.scene_type or "forward")


def _build_lerf_mask(ctx, p: DatasetParams, attrs: SceneAttrs, spec: dict, reader: dict) -> None:
    """A LERF-mask scene: Gaussian Grouping's GT index, its train / test split."""
    root = Path(spec["source"])
    from cobgs.data.lerf_mask import read_lerf_gt

    gt = read_lerf_gt(root)
    every = _stems(root / "images")
    spec.update(protocol="lerf_mask", lerf_mask=gt.to_json(), objects=gt.prompts,
                views=every, test_views=list(gt.test_views), has_poses=True,
                images={"dir": os.fspath(root / "images"), "names": _names(root / "images")},
                sfm_downscale=p.downscale, scene_type=attrs.scene_type or "360")
    if gt.views_without_gt:
        ctx.log.info("LERF-mask: %d test view(s) have no GT folder: %s", len(gt.views_without_gt),
                     gt.views_without_gt[:10])


def _build_posed(ctx, p: DatasetParams, attrs: SceneAttrs, spec: dict, reader: dict) -> None:
    """A posed layout (transforms, Blender, COLMAP, LLFF) with its masks."""
    from cobgs.data.readers import read_scene

    root = Path(spec["source"])
    kw = {"background": tuple(p.background)} if p.background is not None else {}
    scene = read_scene(root, format=reader["format"], downscale=p.downscale,
                       test_every=p.test_every, **kw)
    spec["notes"] = list(scene.notes)
    all_views = sorted(v.name for v in scene.views)
    kept = set(_subset(all_views, p))
    test = [v.name for v in scene.test if v.name in kept]
    with_gt = sorted({k for v in scene.test for k in v.masks})
    if attrs.kind == "blender":
        spec["has_poses"], spec["images"] = True, None
    else:
        sfm_dir, post = _sfm_images(root, p)
        spec["has_poses"] = True
        spec["images"] = {"dir": os.fspath(sfm_dir), "names": [n for n in _names(sfm_dir)
                                                                if Path(n).stem in kept]}
        spec["sfm_downscale"] = post
    have = sorted({k for v in scene.views for k in v.masks})
    if attrs.kind == "blender":
        _check_blender_objects(ctx, root, have)
        if have == ["object"] and not (root / "masks").is_dir():
            # one object, nothing in front of it: the alpha matte is its whole silhouette
            spec["amodal"] = {"source": "visible", "objects": ["object"]}
    spec.update(views=sorted(kept), test_views=test, objects=have,
                protocol="exact" if with_gt else "none",
                scene_type=attrs.scene_type or ("360" if attrs.kind == "blender" else "forward"))


_BUILDERS = {"synthetic": _build_synthetic, "images": _build_images, "nvos": _build_nvos,
             "lerf_mask": _build_lerf_mask}


def _detect(root: Path) -> str:
    from cobgs.data.readers import detect_format

    fmt = detect_format(root)
    if fmt not in ("colmap", "llff"):
        raise StageInputError(f"{root}: an NVOS scene must be an LLFF scene (sparse/0 or "
                              f"poses_bounds.npy), found a {fmt!r} layout")
    return fmt


def _check(p: DatasetParams) -> None:
    """A synthetic preset the generator knows, before any task runs (the check needs the
    generator's modules: numpy and friends)."""
    from cobgs.data.synth_presets import PRESETS

    if p.preset not in PRESETS:
        raise ValueError(f"preset must be one of {sorted(PRESETS)}, got {p.preset!r}")


STAGE = Stage(
    name="dataset", version=6, run=_run, inputs=(), outputs=("dataset",), params=DatasetParams,
    level=("scene",), resources=Resources(cpus=1),
    description="generate a synthetic scene or ingest an external one (dataset.json)", check=_check,
)

AXIS_SCHEMAS = {"scene": SceneAttrs}
