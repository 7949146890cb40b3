"""Stage ``dataset``: generate a synthetic scene, or ingest an external one, per scene.

The scene's *kind* and location come from the ``scene`` axis attributes
(:class:`SceneAttrs`); how to ingest it from the params (:class:`cobgs.configs.DatasetConfig`);
the builders are the library's (:mod:`cobgs.data.build`). The output
``dataset`` artifact holds ``dataset.json`` (see stages/_common.py) and, for synthetic
scenes, the generated scene itself. External data is only read: the spec points at it by
absolute path (an edit that keeps file times: ``cobgs status --verify-data``).

Kinds:
  synthetic  cobgs.data.synth.scene preset (exact masks; exact-GT protocol)
  transforms NeRF-style transforms.json with masks/<object>/ (exact-GT protocol when masks)
  blender    NeRF-synthetic (alpha = object mask "object"; exact-GT protocol)
  llff       poses_bounds.npy + images_<k>/ (no masks)
  colmap     a COLMAP model + images/ (masks/<object>/ optional)
  images     a folder of images without poses (SfM required)
  nvos       an LLFF scene + the NVOS labels folder (NVOS protocol; target view held out)
  lerf_mask  a LERF-mask scene (LERF-mask protocol; split from images_train/)
  spin       a scene + SPIn-NeRF's annotation release (SPIn-NeRF protocol; every view trains)
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Union

from cobgs.configs import DatasetConfig, Files
from cobgs.data.build import kinds  # (torch-free)
from pipeline import Resources, Stage

from ._common import StageInputError, write_json


@dataclass(frozen=True)
class SceneAttrs:
    """Attributes of a ``scene`` axis value: what the data is and where it lives.

    Attributes:
        kind: one of :func:`cobgs.data.build.kinds` (the builders' and every posed layout).
        path: the data folder (every kind but ``synthetic``); relative paths resolve
            against the workflow file; checked when the workflow loads (fail fast). For
            ``kind = "nvos"`` a missing ``<path>`` is also looked for as
            ``<path>_undistort`` (NeX's copies, as fvdb's ``scenes/fern_undistort``).
        labels: the NVOS labels folder (``kind = "nvos"``): the folder holding ``masks/``,
            ``reference_image/`` and ``scribbles/``, or the ``labels/`` the download
            unpacks (its ``llff/`` sub-folder is read). ``kind = "spin"``: the unpacked
            SPIn-NeRF annotation release (the folder holding ``fern (llff)/`` ...), or the
            scene's own folder of it.
        task: the NVOS task or the SPIn-NeRF scene (fern, room, truck, ...; default: the scene
            value's name), or a list of NVOS tasks on this
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
        if self.kind not in kinds():
            raise ValueError(f"kind must be one of {list(kinds())}, got {self.kind!r}")
        if not isinstance(self.task, str):
            if self.kind != "nvos" or not self.task:
                raise ValueError("a list of tasks (several NVOS tasks on one scene) needs kind 'nvos' and "
                                 "at least one task")
            if len(set(self.task)) != len(self.task):
                raise ValueError(f"task repeats a task: {list(self.task)}")
        if self.scene_type not in ("", "forward", "360"):
            raise ValueError(f"scene_type must be 'forward' or '360', got {self.scene_type!r}")
        if self.kind == "synthetic":
            if self.path is not None or self.labels is not None:  # (unread, but walked for the data fingerprint)
                raise ValueError(f"kind 'synthetic' is generated, not read: it takes no "
                                 f"{'path' if self.path is not None else 'labels'}; remove it, or give the kind "
                                 "of the data in the folder")
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
        if self.kind == "spin":
            if self.labels is None:
                raise ValueError("kind 'spin' needs labels = the SPIn-NeRF annotation folder (the unpacked "
                                 "Multiview-Segmentation-Data, holding 'fern (llff)/' ...)")


def _run(ctx, inputs):
    """dataset.json for one scene (:func:`cobgs.data.build.build_spec`)."""
    from cobgs.data.build import BuildInput, ObjectRequest, build_spec

    p: DatasetConfig = ctx.params
    attrs: SceneAttrs = ctx.item.attrs["scene"]
    objects = []
    for it in ctx.items:
        if "object" not in it.axes:
            continue
        oa = it.attrs.get("object")
        own = oa is not None and (bool(getattr(oa, "prompt", "")) or getattr(oa, "mask_dir", None) is not None)
        objects.append(ObjectRequest(it["object"], getattr(oa, "mask", "") if oa is not None else "", own))
    inp = BuildInput(scene=ctx.item["scene"], kind=attrs.kind, path=attrs.path, out_dir=ctx.out_dir,
                     labels=attrs.labels, task=attrs.task, scene_type=attrs.scene_type, objects=tuple(objects))
    try:
        spec = build_spec(inp, p)
    except ValueError as exc:  # (InputError) the data lacks what the kind needs: the message names it
        raise StageInputError(str(exc)) from exc
    write_json(ctx.out_dir / Files.DATASET, spec)
    ctx.log.info("dataset %s (%s): %d views, %d held out, objects %s, protocol %s", spec["scene"], attrs.kind,
                 len(spec["views"]), len(spec["test_views"]), spec["objects"], spec["protocol"])
    ctx.note(kind=attrs.kind, views=len(spec["views"]), test_views=len(spec["test_views"]),
             objects=spec["objects"], protocol=spec["protocol"], scene_type=spec["scene_type"])
    return {"dataset": ctx.out_dir}


def _check(p: DatasetConfig) -> None:
    """A synthetic preset the generator knows, before any task runs (the check needs the
    generator's modules: numpy and friends)."""
    from cobgs.data.synth.presets import PRESETS

    if p.preset not in PRESETS:
        raise ValueError(f"preset must be one of {sorted(PRESETS)}, got {p.preset!r}")


STAGE = Stage(
    name="dataset", version=6, run=_run, inputs=(), outputs=("dataset",), params=DatasetConfig,
    level=("scene",), resources=Resources(cpus=1),
    description="generate a synthetic scene or ingest an external one (dataset.json)", check=_check,
)

AXIS_SCHEMAS = {"scene": SceneAttrs}
