"""What the stages share: the artifact layouts they exchange, and reading them back.

Artifacts (each a folder inside a cache entry; the file names below are stable, named once in
:class:`cobgs.configs.Files` and documented in docs/usage.md "What the cache holds"):

* ``dataset`` — ``dataset.json`` (the spec below) and, for synthetic scenes, the generated
  scene in ``scene/``. External data stays where it is and is referenced by absolute path
  (it is never written to).
* ``poses`` — ``sfm.json``; when SfM ran also ``images/`` (undistorted, PINHOLE) and
  ``sparse/0/`` (cobgs.data.sfm's layout).
* ``scene`` (train) — ``scene.ply`` (standard 3DGS), ``train.json``, ``renders/<view>.png``.
* ``masks`` — ``<view>.png`` (0/255, one per training view), ``masks.json``.
* ``refined`` — ``refined.ply`` (with label extras), ``segmentation.npz``, ``refine.json``,
  ``stage_scores.npz``.
* ``segmentation`` — ``object.ply``, ``background.ply`` (standard 3DGS), per held-out view
  ``pred_masks/``, ``render/``, ``object/``, ``removed/`` PNGs, ``segment.json``.
* ``metrics`` — ``metrics.json``, ``per_view.csv``.
* ``summary`` — ``summary.json``, ``summary.csv``, ``by_method.csv``, ``timings.csv``.

The dataset spec (``dataset.json``, format ``cobgs-dataset`` version 1) is what lets every
later stage load the same posed views: the reader and its options, the view names kept,
the held-out names, the objects with ground truth and the evaluation protocol.
"""

from __future__ import annotations

from cobgs.configs import Files
import json
import os
from pathlib import Path
from typing import Any, Mapping, Optional

from pipeline import PipelineError

SPEC_FILE = Files.DATASET
from cobgs.data.spec import FORMAT as SPEC_FORMAT, VERSION as SPEC_VERSION, DatasetSpec  # noqa: E402


class StageInputError(PipelineError):
    """A stage got inputs or params it cannot work with (the message says which)."""


# -- JSON ------------------------------------------------------------------------------------
def write_json(path: Path, data: Any) -> Path:
    """Write JSON (non-finite floats as null, paths as strings); the engine makes the
    entry atomic, so a plain write inside ``ctx.out_dir`` is enough."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", encoding="utf-8") as f:
        json.dump(_jsonable(data), f, indent=1, sort_keys=False)
        f.write("\n")
    return path


def _jsonable(v: Any) -> Any:
    import dataclasses
    import math

    import numpy as np

    if dataclasses.is_dataclass(v) and not isinstance(v, type):
        return _jsonable(dataclasses.asdict(v))
    if isinstance(v, Mapping):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, Path):
        return os.fspath(v)
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (np.floating, float)):
        f = float(v)
        return f if math.isfinite(f) else None
    if isinstance(v, np.ndarray):
        return _jsonable(v.tolist())
    return v


def read_json(path: Path) -> Any:
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except FileNotFoundError:
        raise StageInputError(f"{path}: missing (is the upstream artifact complete?)") from None
    except (OSError, ValueError) as exc:
        raise StageInputError(f"{path}: unreadable JSON: {exc}") from None


# -- the dataset spec ------------------------------------------------------------------------
def read_spec(dataset_dir: Path) -> DatasetSpec:
    """The dataset stage's ``dataset.json`` as the typed record (:class:`cobgs.data.spec.DatasetSpec`)."""
    spec = DatasetSpec(read_json(Path(dataset_dir) / SPEC_FILE))
    if spec.get("format") != SPEC_FORMAT or spec.get("version") != SPEC_VERSION:
        raise StageInputError(f"{dataset_dir / SPEC_FILE}: expected format {SPEC_FORMAT!r} "
                              f"version {SPEC_VERSION}, got {spec.get('format')!r} "
                              f"version {spec.get('version')!r}")
    return spec


def spec_path(dataset_dir: Path, value: Optional[str]) -> Optional[Path]:
    """A path from the spec: relative ones live inside the dataset artifact."""
    if value is None:
        return None
    p = Path(value)
    return p if p.is_absolute() else Path(dataset_dir) / p


def sfm_ran(poses_dir: Path) -> bool:
    return (Path(poses_dir) / Files.SFM_MODEL).is_dir()


def load_scene(dataset_dir: Path, poses_dir: Optional[Path]):
    """The posed views of a scene, split as the dataset spec says.

    With an SfM model in ``poses_dir`` the cameras come from it (images undistorted by
    SfM; masks from the SfM artifact's ``masks/`` when the camera had distortion, which
    the SfM stage undistorted like the images, else from the dataset's ``masks/``
    folders, which a pinhole undistortion leaves in place); otherwise the dataset's own
    reader is used. Views not in the spec's ``views`` list are dropped.

    Returns:
        :class:`cobgs.data.scene.Scene`.
    """
    from cobgs.data.readers import read_scene

    dataset_dir = Path(dataset_dir)
    spec = read_spec(dataset_dir)
    rd = spec.reader
    root = spec_path(dataset_dir, rd.get("path"))
    test = list(spec.test_views)
    if poses_dir is not None and sfm_ran(poses_dir):
        from cobgs.data.colmap import read_colmap

        poses_dir = Path(poses_dir)
        # masks undistorted by the SfM stage (a distorted camera) replace the dataset's
        mask_root = poses_dir if (poses_dir / "masks").is_dir() or root is None else root
        scene = read_colmap(mask_root, images_dir=poses_dir / Files.SFM_IMAGES, model_dir=poses_dir / Files.SFM_MODEL,
                            downscale=float(spec.sfm_downscale), test_names=test or None,
                            test_every=0)
    else:
        if rd.get("format") is None:
            raise StageInputError(f"dataset {spec.get('kind')!r} at {root} has no poses and SfM did not run "
                                  "(sfm.mode is 'never'?): set sfm.mode to 'auto' or 'always'")
        kw = {}
        if rd.get("background") is not None:
            kw["background"] = tuple(rd["background"])
        from cobgs.data.formats import scene_format

        if not scene_format(rd["format"]).own_split:
            kw["test_names"] = test or None
            kw["test_every"] = 0
        if rd.get("distortion"):
            kw["distortion"] = rd["distortion"]
        scene = read_scene(root, format=rd["format"], downscale=float(rd.get("downscale", 1.0)), **kw)
        pts = Path(poses_dir) / Files.SFM_POINTS if poses_dir is not None else None
        if (scene.points is None or len(scene.points) == 0) and pts is not None and pts.is_file():
            import numpy as np
            import torch

            with np.load(pts) as z:  # triangulated by the SfM stage with the known poses
                scene.points = torch.from_numpy(z["xyz"].astype(np.float32))
                scene.points_rgb = torch.from_numpy(z["rgb"].astype(np.float32) / 255.0)
    keep = set(spec.views)
    if spec.protocol == "spin":
        _attach_spin_masks(scene, spec.spin)
    scene.train = [v for v in scene.train if v.name in keep]
    scene.test = [v for v in scene.test if v.name in keep]
    if not scene.train:
        raise StageInputError(f"no training view left for dataset {dataset_dir} (views kept: {len(keep)})")
    return scene


def _attach_spin_masks(scene, spin: dict) -> None:
    """SPIn-NeRF's GT masks as the views' masks of ``object`` (the ``files`` route's upper bound
    reads them), each resized NEAREST to its view's size (:func:`cobgs.evaluate.protocols.spin_binary`)."""
    import numpy as np
    import torch

    from cobgs.evaluate.protocols import read_mask_u8, resize_nearest, spin_binary

    for v in scene.views:
        f = spin["masks"].get(v.name)
        if f is not None:
            m = resize_nearest(spin_binary(read_mask_u8(f)).astype(np.uint8) * 255, v.height, v.width)
            v.masks["object"] = torch.from_numpy(np.ascontiguousarray(m > 127))


def object_name(ctx) -> str:
    """The dataset object an ``object`` item stands for (its ``mask`` attribute or its name)."""
    attrs = ctx.item.attrs.get("object")
    name = getattr(attrs, "mask", "") if attrs is not None else ""
    return name or ctx.item["object"]


def nvos_task(spec: DatasetSpec, *names: str) -> dict:
    """The NVOS task an object of an NVOS scene stands for (:meth:`DatasetSpec.nvos_task`),
    or a clear error when the scene's tasks do not include it."""
    task = spec.nvos_task(*names)
    if task is None:
        raise StageInputError(f"NVOS scene {spec.scene!r} holds the tasks {sorted(spec.nvos_tasks)}; object "
                              f"{' / '.join(repr(n) for n in names)} is none of them (name the object after its task)")
    return task


# -- images ----------------------------------------------------------------------------------
def write_png(path: Path, array) -> Path:
    """Write an 8-bit PNG: [H, W] (grey) or [H, W, 3] RGB; bool -> 0/255, float [0, 1] -> 8 bit."""
    import cv2
    import numpy as np

    a = np.asarray(array)
    if a.dtype == np.bool_:
        a = a.astype(np.uint8) * 255
    elif a.dtype != np.uint8:
        a = np.clip(np.rint(a.astype(np.float64) * 255.0), 0, 255).astype(np.uint8)
    if a.ndim == 3:
        a = a[:, :, ::-1]
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(os.fspath(path), np.ascontiguousarray(a)):
        import errno
        import shutil

        # libpng says nothing of why: a full disk is told apart by the space left (so that the run
        # stops as for any full disk, rather than failing task after task)
        if shutil.disk_usage(path.parent).free < max(1 << 20, 2 * a.nbytes):
            raise OSError(errno.ENOSPC, "No space left on device (OpenCV could not write the PNG)", os.fspath(path))
        raise StageInputError(f"{path}: could not write PNG")
    return path


def read_mask_png(path: Path, width: int, height: int):
    """A 0/255 mask file as a [height, width] bool tensor (area-resized, >= 0.5)."""
    import cv2
    import numpy as np
    import torch

    arr = cv2.imread(os.fspath(path), cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION)
    if arr is None:
        raise StageInputError(f"{path}: missing or unreadable mask PNG")
    m = (arr >= 128).astype(np.float32)
    if m.shape != (height, width):
        m = cv2.resize(m, (width, height), interpolation=cv2.INTER_AREA)
    return torch.from_numpy(m >= 0.5)


def masks_for_views(masks_dir: Path, views) -> list:
    """One bool mask per view from ``<masks_dir>/<view>.png`` (None where there is none)."""
    out = []
    for v in views:
        p = Path(masks_dir) / f"{v.name}.png"
        out.append(read_mask_png(p, v.width, v.height) if p.is_file() else None)
    return out


# -- device ----------------------------------------------------------------------------------
def torch_device(device: str):
    """The torch device of the workflow's ``device`` setting, checked."""
    import torch

    if device.startswith("cuda") and not torch.cuda.is_available():
        raise StageInputError(f"the workflow asks for device {device!r} but this torch build "
                              f"({torch.__version__}) sees no CUDA device; run with --set device=cpu")
    return torch.device(device)


def to_device(scene, device: str):
    """Move the cameras and images of a scene to ``device`` (in place; CPU is a no-op)."""
    import torch

    dev = torch_device(device)
    if dev.type == "cpu":
        return scene
    for v in scene.views:
        v.camera = v.camera.to(dev)
        v.image = v.image.to(dev)
        v.masks = {k: m.to(dev) for k, m in v.masks.items()}
    return scene


def scene_cameras(dataset_dir: Path, poses_dir: Optional[Path]) -> tuple[list, tuple]:
    """(training cameras, background colour) of a scene: what an orbit around an object
    needs (turntables). Loads the scene once; callers keep it per scene."""
    scene = load_scene(Path(dataset_dir), Path(poses_dir) if poses_dir else None)
    return [v.camera for v in scene.train], tuple(scene.background)
