"""dataset.json from a scene's data: one builder per kind (the dataset stage's library side).

:func:`build_spec` fills the scene's record (:class:`cobgs.data.spec.DatasetSpec`): its views
and held-out views, objects, protocol, the folder SfM reads, how later stages read the
scene. Kinds: each posed layout of :data:`cobgs.data.formats.FORMATS`, read by its reader
(transforms.json, NeRF-synthetic / Blender with its alpha as the mask of "object", LLFF, a COLMAP
model; masks/<object>/ where the data has them), and the kinds built here:

  synthetic  cobgs.data.synth.scene preset, generated into ``out_dir/scene`` (exact masks)
  images     a folder of images without poses (SfM required)
  nvos       an LLFF scene + the NVOS labels folder (NVOS protocol; target view held out)
  lerf_mask  a LERF-mask scene (LERF-mask protocol; split from images_train/)
  spin       a scene + SPIn-NeRF's multiview annotations (SPIn-NeRF protocol; every view trains)

External data is only read: the spec points at it by absolute path.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Union

from cobgs.configs import DatasetConfig
from cobgs.data.formats import FORMATS, scene_format
from cobgs.data.spec import FORMAT as SPEC_FORMAT, VERSION as SPEC_VERSION
from cobgs.errors import InputError

log = logging.getLogger(__name__)

#: The reader format of the kinds built otherwise than from a posed layout: None where the scene
#: has no poses of its own (SfM finds them) or its builder sets it (NVOS: the LLFF copy's).
_BUILT_FORMATS = {"synthetic": None, "images": None, "nvos": None, "lerf_mask": "colmap", "spin": None}
def kinds() -> tuple[str, ...]:
    """Every dataset kind: the builders' and each posed layout of :data:`cobgs.data.formats.FORMATS`
    (a new layout is a new kind, with no line here)."""
    return ("synthetic", *FORMATS, "images", "nvos", "lerf_mask", "spin")


KINDS = kinds()  # (the shipped ones; a layout registered later: kinds())
_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


@dataclass(frozen=True)
class ObjectRequest:
    """An object a workflow asks of the scene: its name, the dataset object it stands for
    (``mask``), and whether it brings its own masks (a text prompt or a mask folder)."""

    name: str
    mask: str = ""
    own_masks: bool = False


@dataclass(frozen=True)
class BuildInput:
    """What :func:`build_spec` needs beside the config: the scene's name, kind and folder, the
    NVOS fields, the scene type asked for, where generated data go, the objects asked for."""

    scene: str
    kind: str
    path: Optional[Path] = None
    out_dir: Path = Path(".")
    labels: Optional[Path] = None
    task: Union[str, tuple[str, ...]] = ""
    scene_type: str = ""
    objects: tuple[ObjectRequest, ...] = field(default_factory=tuple)


def build_spec(inp: BuildInput, p: DatasetConfig) -> dict:
    """The scene's record (dataset.json's content) for ``inp`` read with ``p``.

    Raises:
        InputError, DataError: the data does not hold what the kind needs (named).
    """
    spec: dict = {"format": SPEC_FORMAT, "version": SPEC_VERSION, "scene": inp.scene, "kind": inp.kind,
                  "protocol": "none", "objects": [], "sfm_downscale": 1.0}
    reader: dict = {"format": inp.kind if inp.kind in FORMATS else _BUILT_FORMATS.get(inp.kind), "path": None,
                    "downscale": p.downscale,
                    "background": None if p.background is None else list(p.background)}
    if inp.kind != "synthetic":
        root = Path(inp.path).resolve()
        spec["source"] = os.fspath(root)
        reader["path"] = os.fspath(root)
    _BUILDERS.get(inp.kind, _build_posed)(inp, p, spec, reader)
    if spec.get("images") and inp.kind != "synthetic":
        # one reading of "up" for SfM, masks and clicks: rotated photos are refused (cobgs.data.images)
        from cobgs.data.images import check_upright

        d = Path(spec["images"]["dir"])
        folder = d if d.is_absolute() else inp.out_dir / d
        check_upright([folder / n for n in spec["images"]["names"]], "photo")
    if inp.kind not in ("synthetic", "nvos", "lerf_mask", "spin") and spec.get("source"):
        check_mask_folders(Path(spec["source"]) / "masks", spec.get("views") or [],
                           [o.mask or o.name for o in inp.objects if not o.own_masks])
    spec["reader"] = reader
    return spec


#: How many names a message shows.
_SHOWN = 3


def check_mask_folders(masks_root: Path, views: list, asked: list) -> None:
    """The scene's own ``masks/<object>/`` folders, before SfM and training: every mask file
    stored upright (an EXIF orientation tag would turn it for one reader and not another,
    :mod:`cobgs.data.images`), and each folder of an object the workflow asks for holding at
    least one mask named after a photo (``masks/<object>/<photo stem>.png``).

    Raises:
        DataError: a mask with an orientation tag (naming the file and the tag).
        InputError: an asked object's folder where no file is named after a photo (examples of
            both names).
    """
    from cobgs.data.images import check_upright

    if not masks_root.is_dir():
        return
    stems = set(views)
    for folder in sorted(p for p in masks_root.iterdir() if p.is_dir()):
        files = sorted(f for f in folder.iterdir() if f.is_file() and f.suffix.lower() in _MASK_SUFFIXES)
        check_upright(files, "mask file")
        if folder.name in asked and files and stems and not any(f.stem in stems for f in files):
            raise InputError(f"{folder}: no mask file is named after a photo: masks are "
                             f"masks/{folder.name}/<photo name>.png, e.g. {sorted(stems)[0]}.png for the photo "
                             f"{sorted(stems)[0]}; the folder holds {[f.name for f in files[:_SHOWN]]}, the photos "
                             f"are {sorted(stems)[:_SHOWN]}")


_MASK_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")


def _stems(folder: Path) -> list[str]:
    if not folder.is_dir():
        raise InputError(f"{folder}: image folder not found")
    return sorted(p.stem for p in folder.iterdir() if p.is_file() and p.suffix.lower() in _IMAGE_SUFFIXES)


def _names(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.is_file() and p.suffix.lower() in _IMAGE_SUFFIXES)


def _subset(names: list[str], p: DatasetConfig) -> list[str]:
    out = names[:: p.view_stride]
    return out[: p.max_views] if p.max_views else out


def _every(names: list[str], k: int) -> list[str]:
    return [n for i, n in enumerate(names) if k and i % k == 0]


def _sfm_images(root: Path, p: DatasetConfig) -> tuple[Path, float]:
    """(folder SfM reads, downscale applied to its images afterwards)."""
    if p.images_dir:
        d = root / p.images_dir
        if not d.is_dir():
            raise InputError(f"dataset.images_dir: {d} does not exist")
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


def _check_alpha_objects(inp: "BuildInput", root: Path, have: list, alpha: str) -> None:
    """The objects of a layout whose images' alpha channel is an object's mask (NeRF-synthetic:
    ``object``) come from that channel or ``masks/<object>/`` folders; an object the workflow
    asks for that neither gives fails here, in the first task, naming the folder (objects with
    a text prompt are exempt)."""
    for obj in inp.objects:
        name = obj.mask or obj.name
        if name in have or obj.own_masks:
            continue
        why = ", ".join(w for w in ("its images have no alpha channel" if alpha not in have else "",
                                    f"it has masks of {have} only" if have else "") if w)
        raise InputError(f"object {obj.name!r} of scene {inp.scene!r}: {root} gives no "
                              f"mask of {name!r} ({why}, and there is no masks/{name}/ folder); add "
                              f"masks/{name}/<image>.png, or set the object's mask / prompt")




def _build_synthetic(inp: "BuildInput", p: DatasetConfig, spec: dict, reader: dict) -> None:
    """A synthetic scene, generated into the artifact (exact GT, amodal masks)."""
    from cobgs.data.synth.scene import generate_scene

    out = generate_scene(inp.out_dir / "scene", p.preset, p.seed, progress=False,
                         width_px=p.width_px or None, height_px=p.height_px or None,
                         num_views=p.num_views or None, supersampling=p.supersampling or None,
                         workers=p.workers)
    meta = json.loads((out / "scene.json").read_text(encoding="utf-8"))
    tf = json.loads((out / "transforms.json").read_text(encoding="utf-8"))
    reader.update(format="transforms", path="scene")
    views = [Path(f["file_path"]).stem for f in tf["frames"]]
    test = [Path(f).stem for f in tf.get("test_filenames", [])]
    spec.update(protocol="exact", synthetic={k: meta[k] for k in ("preset", "seed", "trajectory",
                                                                    "image_size", "supersampling",
                                                                    "num_views")},
                objects=[o["name"] for o in meta["objects"] if o.get("target", True)],
                distractors=[o["name"] for o in meta["objects"] if not o.get("target", True)],
                scene_type=inp.scene_type or ("360" if meta["trajectory"] == "orbit" else "forward"),
                images={"dir": "scene/images", "names": [Path(f["file_path"]).name for f in tf["frames"]]},
                has_poses=True,
                amodal={"source": "files", "dir": "scene/amodal",
                        "objects": [o["name"] for o in meta["objects"]]})
    kept = _subset(views, p)
    spec.update(views=kept, test_views=[v for v in test if v in set(kept)])


def _build_images(inp: "BuildInput", p: DatasetConfig, spec: dict, reader: dict) -> None:
    """Photos without poses: SfM finds them."""
    root = Path(spec["source"])
    sfm_dir, post = _sfm_images(root, p)
    names = _subset(_names(sfm_dir), p)
    stems = [Path(n).stem for n in names]
    spec.update(views=stems, test_views=_every(stems, p.test_every), has_poses=False,
                images={"dir": os.fspath(sfm_dir), "names": names}, sfm_downscale=post,
                scene_type=inp.scene_type or "360")


def _build_nvos(inp: "BuildInput", p: DatasetConfig, spec: dict, reader: dict) -> None:
    """An LLFF scene and the NVOS labels: one or several tasks, their targets held out."""
    from cobgs.data.readers import read_scene

    root = Path(spec["source"])
    name = inp.scene
    from cobgs.data.nvos import read_nvos_task

    names = (inp.task or name,) if isinstance(inp.task, str) else inp.task
    tasks = [read_nvos_task(inp.labels, t) for t in names]
    task = tasks[0]
    targets = sorted({t.target for t in tasks})
    for t in tasks:
        if t.reference in targets:
            raise InputError(f"NVOS task {t.task!r}: its reference view {t.reference!r} is "
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
                raise InputError(f"NVOS task {t.task!r}: view {need!r} is not an image of "
                                      f"{root} (images: {stems[:3]} ...)")
    sfm_dir, post = _sfm_images(root, p)
    sfm_dir = _sfm_images_as_views(inp.out_dir, scene, sfm_dir)
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
                                        else inp.out_dir / sfm_dir)},
                sfm_downscale=post,
                scene_type=inp.scene_type or "forward")


def _build_lerf_mask(inp: "BuildInput", p: DatasetConfig, spec: dict, reader: dict) -> None:
    """A LERF-mask scene: Gaussian Grouping's GT index, its train / test split."""
    root = Path(spec["source"])
    from cobgs.data.lerf_mask import read_lerf_gt

    gt = read_lerf_gt(root)
    every = _stems(root / "images")
    spec.update(protocol="lerf_mask", lerf_mask=gt.to_json(), objects=gt.prompts,
                views=every, test_views=list(gt.test_views), has_poses=True,
                images={"dir": os.fspath(root / "images"), "names": _names(root / "images")},
                sfm_downscale=p.downscale, scene_type=inp.scene_type or "360")
    if gt.views_without_gt:
        log.info("LERF-mask: %d test view(s) have no GT folder: %s", len(gt.views_without_gt),
                 gt.views_without_gt[:10])


def _build_spin(inp: "BuildInput", p: DatasetConfig, spec: dict, reader: dict) -> None:
    """A scene and its SPIn-NeRF annotations (:mod:`cobgs.data.spin`): every view trains (the
    peers train on the whole capture and score the annotated views but the prompt's).

    The RGB is the scene's published copy: an LLFF or COLMAP layout (nerf_llff_data, NeX's,
    nerf_real_360, Tanks and Temples' tandt_db) read as NVOS reads it (the captured frame), or
    a folder of images without poses (``rgb/`` or ``images/``: SfM finds the cameras)."""
    from cobgs.data.readers import detect_format, read_scene
    from cobgs.data.spin import image_size, read_spin_scene

    root = Path(spec["source"])
    scene_key = (inp.task if isinstance(inp.task, str) and inp.task else inp.scene).lower()
    try:
        fmt = detect_format(root)
    except Exception:  # (no poses of its own)
        fmt = None
    if fmt in ("colmap", "llff"):
        reader.update(format=fmt, distortion="ignore")
        scene = read_scene(root, format=fmt, downscale=p.downscale, test_every=0, distortion="ignore")
        paths = {v.name: Path(v.path) for v in scene.views}
        sfm_dir, post = _sfm_images(root, p)
        sfm_dir = _sfm_images_as_views(inp.out_dir, scene, sfm_dir)
        spec["notes"] = list(scene.notes)
        spec["has_poses"] = True
    else:
        folder = root / (p.images_dir or ("rgb" if (root / "rgb").is_dir() else "images"))
        if not folder.is_dir():
            raise InputError(f"{root}: SPIn-NeRF scene {scene_key!r} has no LLFF / COLMAP layout and no "
                             "rgb/ or images/ folder of photos")
        paths = {Path(n).stem: folder / n for n in _names(folder)}
        sfm_dir, post = folder, p.downscale
        spec["has_poses"] = False
    ann = read_spin_scene(inp.labels, scene_key, list(paths), view_size=lambda v: image_size(paths[v]))
    stems = sorted(paths)
    spec.update(protocol="spin", spin=ann.to_json(), objects=["object"], views=stems, test_views=[],
                images={"dir": os.fspath(sfm_dir),
                        "names": _names(sfm_dir if sfm_dir.is_absolute() else inp.out_dir / sfm_dir)},
                sfm_downscale=post, scene_type=inp.scene_type or ("forward" if fmt == "llff" or
                                                                  "(llff)" in ann.folder.name else "360"))
    spec.setdefault("notes", []).append(
        f"SPIn-NeRF {scene_key}: {len(ann.masks)} annotated views ({ann.rule} names), prompt view "
        f"{ann.prompt!r} ({ann.mask_names[ann.prompt]}), {len(ann.scored)} scored; every view trains")


def _build_posed(inp: "BuildInput", p: DatasetConfig, spec: dict, reader: dict) -> None:
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
    fmt = scene_format(reader["format"], root)
    if not fmt.images_folder:
        spec["has_poses"], spec["images"] = True, None
    else:
        sfm_dir, post = _sfm_images(root, p)
        spec["has_poses"] = True
        spec["images"] = {"dir": os.fspath(sfm_dir), "names": [n for n in _names(sfm_dir)
                                                                if Path(n).stem in kept]}
        spec["sfm_downscale"] = post
    have = sorted({k for v in scene.views for k in v.masks})
    if fmt.alpha_object:
        _check_alpha_objects(inp, root, have, fmt.alpha_object)
        if have == [fmt.alpha_object] and not (root / "masks").is_dir():
            # one object, nothing in front of it: the alpha matte is its whole silhouette
            spec["amodal"] = {"source": "visible", "objects": [fmt.alpha_object]}
    spec.update(views=sorted(kept), test_views=test, objects=have,
                protocol="exact" if with_gt else "none", scene_type=inp.scene_type or fmt.scene_type)


_BUILDERS = {"synthetic": _build_synthetic, "images": _build_images, "nvos": _build_nvos,
             "lerf_mask": _build_lerf_mask, "spin": _build_spin}


def _detect(root: Path) -> str:
    from cobgs.data.readers import detect_format

    fmt = detect_format(root)
    if fmt not in ("colmap", "llff"):
        raise InputError(f"{root}: an NVOS scene must be an LLFF scene (sparse/0 or "
                         f"poses_bounds.npy), found a {fmt!r} layout")
    return fmt
