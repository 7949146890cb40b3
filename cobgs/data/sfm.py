"""Structure from motion with pycolmap (4.x): images in, COLMAP model + undistorted images out.

:func:`run_sfm` runs SIFT extraction, exhaustive or sequential matching, incremental
mapping, keeps the largest model and undistorts it to PINHOLE. It writes the layout the
3DGS tools use (COLMAP's ``image_undistorter`` output plus the distorted model)::

    <out>/images/<name>            undistorted images (PINHOLE camera)
    <out>/sparse/0/{cameras,images,points3D}.bin   undistorted model (binary)
    <out>/distorted/sparse/0/*.bin the model before undistortion
    <out>/distorted/database.db    features and matches
    <out>/sfm.json                 summary: registered / unregistered images, timings

The folder is built under a temporary sibling name and renamed into place last, so an
interrupted run never leaves a folder that looks finished. Reading the model into library
cameras is :mod:`cobgs.data.colmap`'s job.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

from cobgs.configs import Files, SfmOptions
from cobgs.data.images import list_images
from cobgs.errors import DataError, InputError

SFM_IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")  # what COLMAP reads
_MAX_NAMES_IN_ERROR = 30


@dataclass(frozen=True)
class SfmResult:
    """What :func:`run_sfm` produced.

    Attributes:
        root: the output folder.
        model_dir: ``root/sparse/0``, the undistorted PINHOLE model (binary).
        image_dir: ``root/images``, the undistorted images.
        registered: names of the images with a pose, sorted.
        unregistered: names of the input images without one, sorted.
        num_models: reconstructions the mapper produced (the largest is kept).
        num_points3d: 3D points of the kept model.
        mean_reprojection_error_px: mean reprojection error of the kept model.
        matcher: the matcher actually used ("exhaustive" or "sequential").
        timings_s: seconds per step: extract, match, map, undistort, total.
    """

    root: Path
    model_dir: Path
    image_dir: Path
    registered: Tuple[str, ...]
    unregistered: Tuple[str, ...]
    num_models: int
    num_points3d: int
    mean_reprojection_error_px: float
    matcher: str
    timings_s: Dict[str, float] = field(default_factory=dict)

    @property
    def registered_fraction(self) -> float:
        n = len(self.registered) + len(self.unregistered)
        return len(self.registered) / n if n else 0.0

    def to_json(self) -> dict:
        d = dataclasses.asdict(self)
        for k in ("root", "model_dir", "image_dir"):
            d[k] = str(d[k])
        d["registered"], d["unregistered"] = list(self.registered), list(self.unregistered)
        return d


def sfm_image_names(image_dir: Path) -> List[str]:
    """The image file names SfM takes from ``image_dir`` (the formats COLMAP reads), sorted.

    Raises:
        InputError: the folder does not exist. DataError: it holds no such image.
    """
    if not Path(image_dir).is_dir():
        raise InputError(f"image folder {image_dir} does not exist")
    names = [p.name for p in list_images(image_dir, SFM_IMAGE_EXTENSIONS)]
    if not names:
        raise DataError(f"no images ({', '.join(SFM_IMAGE_EXTENSIONS)}) found", image_dir)
    return names


def _name_list(names: Sequence[str]) -> str:
    shown = ", ".join(names[:_MAX_NAMES_IN_ERROR])
    more = len(names) - _MAX_NAMES_IN_ERROR
    return shown + (f" ... and {more} more" if more > 0 else "")


def _prepare_out(out: Path) -> None:
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError(f"SfM output folder {out} exists and is not empty")
    out.parent.mkdir(parents=True, exist_ok=True)


def _extraction_options(pycolmap, options: SfmOptions, threads: int):
    """SIFT extraction options of :func:`run_sfm` and :func:`triangulate_known_poses`."""
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = threads
    extraction.use_gpu = options.device == "cuda"
    extraction.max_image_size = options.max_image_size_px
    extraction.sift.max_num_features = options.max_num_features
    return extraction


def _matching_options(pycolmap, options: SfmOptions, threads: int):
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = threads
    matching.use_gpu = options.device == "cuda"
    return matching


def check_camera(pycolmap, options: SfmOptions) -> None:
    """Raise InputError for an unknown camera model or a wrong number of its parameters."""
    try:
        probe = pycolmap.Camera.create_from_model_name(1, options.camera_model, 1.0, 2, 2)
    except (ValueError, RuntimeError):
        raise InputError(f"SfmOptions.camera_model {options.camera_model!r} is not a COLMAP "
                         "camera model (e.g. SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, OPENCV)") from None
    if options.camera_params is not None and len(options.camera_params) != len(probe.params):
        raise InputError(f"SfmOptions.camera_params must have {len(probe.params)} values for "
                         f"{options.camera_model} ({probe.params_info}), got "
                         f"{len(options.camera_params)}")


def _to_pinhole(rec) -> None:
    """Turn SIMPLE_PINHOLE cameras of ``rec`` into the equivalent PINHOLE, in place."""
    from cobgs.data.pycolmap_import import import_pycolmap

    pycolmap = import_pycolmap()

    for cam in rec.cameras.values():
        if cam.model == pycolmap.CameraModelId.SIMPLE_PINHOLE:
            f, cx, cy = (float(v) for v in cam.params)
            cam.model = pycolmap.CameraModelId.PINHOLE
            cam.params = [f, f, cx, cy]
        elif cam.model != pycolmap.CameraModelId.PINHOLE:
            raise DataError(f"undistorted camera {cam.camera_id} has model {cam.model.name}, "
                            "expected PINHOLE")


def run_sfm(image_dir: os.PathLike | str, out_dir: os.PathLike | str,
            options: SfmOptions = SfmOptions(),
            image_names: Optional[Sequence[str]] = None) -> SfmResult:
    """Reconstruct cameras and sparse points from the images in ``image_dir``.

    Args:
        image_dir: folder of images (read only).
        out_dir: new (or empty) folder for the result, see the module docstring.
        options: see :class:`SfmOptions`.
        image_names: the images to use (names inside ``image_dir``); all images if None.
    Returns:
        A :class:`SfmResult`.
    Raises:
        DataError: no model could be built, or fewer than
            ``options.min_registered_fraction`` of the images registered; the message
            names the unregistered images.
    """
    from cobgs.data.pycolmap_import import import_pycolmap

    pycolmap = import_pycolmap()

    image_dir = Path(image_dir)
    out = Path(out_dir)
    all_names = sfm_image_names(image_dir)
    if image_names is not None:
        missing = sorted(set(image_names) - set(all_names))
        if missing:
            raise InputError(f"image_names not found in {image_dir}: {_name_list(missing)}")
        names = sorted(set(image_names))
    else:
        names = all_names
    if len(names) < 2:
        raise DataError(f"SfM needs at least 2 images, got {len(names)}", image_dir)
    check_camera(pycolmap, options)
    _prepare_out(out)
    threads = options.threads()
    device = pycolmap.Device.cuda if options.device == "cuda" else pycolmap.Device.cpu
    if options.device == "cuda" and not pycolmap.has_cuda:
        raise InputError("SfmOptions.device='cuda' but this pycolmap build has no CUDA")
    matcher = options.matcher
    if matcher == "auto":
        matcher = "exhaustive" if len(names) <= options.exhaustive_max_images else "sequential"

    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 0 if options.verbose else 1
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    timings: Dict[str, float] = {}
    t_start = time.perf_counter()
    try:
        pycolmap.set_random_seed(options.seed)
        dist = tmp / "distorted"
        dist.mkdir()
        db = dist / "database.db"

        t0 = time.perf_counter()
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = options.camera_model
        if options.camera_params is not None:
            reader.camera_params = ",".join(repr(float(v)) for v in options.camera_params)
        pycolmap.extract_features(
            db, image_dir, image_names=names,
            camera_mode=pycolmap.CameraMode.SINGLE if options.single_camera else pycolmap.CameraMode.AUTO,
            reader_options=reader, extraction_options=_extraction_options(pycolmap, options, threads),
            device=device)
        timings["extract"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        matching = _matching_options(pycolmap, options, threads)
        if matcher == "exhaustive":
            pycolmap.match_exhaustive(db, matching_options=matching, device=device)
        else:
            pairing = pycolmap.SequentialPairingOptions()
            pairing.overlap = options.sequential_overlap
            pairing.num_threads = threads
            # Loop detection needs a vocabulary tree file, which is not shipped offline.
            pairing.loop_detection = False
            pycolmap.match_sequential(db, matching_options=matching, pairing_options=pairing,
                                      device=device)
        timings["match"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        mapper = pycolmap.IncrementalPipelineOptions()
        mapper.num_threads = threads
        mapper.random_seed = options.seed
        mapper.min_num_matches = options.min_num_matches
        # COLMAP discards sub-models under 10 images; a smaller input must still be able
        # to produce a model.
        mapper.min_model_size = min(mapper.min_model_size, len(names))
        mapper.ba_use_gpu = False
        mapper_dir = tmp / "mapper"
        mapper_dir.mkdir()
        models = pycolmap.incremental_mapping(db, image_dir, mapper_dir, options=mapper)
        timings["map"] = time.perf_counter() - t0
        if not models:
            raise DataError(f"pycolmap built no model; none of the {len(names)} images registered: "
                            f"{_name_list(names)}", image_dir)
        rec = max(models.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()))
        registered = sorted(rec.images[i].name for i in rec.reg_image_ids())
        unregistered = sorted(set(names) - set(registered))
        frac = len(registered) / len(names)
        if frac < options.min_registered_fraction:
            raise DataError(
                f"SfM registered {len(registered)} of {len(names)} images ({frac:.0%}), fewer "
                f"than the required {options.min_registered_fraction:.0%}; unregistered: "
                f"{_name_list(unregistered)}{_other_sizes(image_dir, names, unregistered)}", image_dir)
        (dist / "sparse" / "0").mkdir(parents=True)
        rec.write_binary(str(dist / "sparse" / "0"))
        num_points = rec.num_points3D()
        reproj = float(rec.compute_mean_reprojection_error())
        shutil.rmtree(mapper_dir)

        t0 = time.perf_counter()
        und = tmp / "undistorted"
        pycolmap.undistort_images(und, dist / "sparse" / "0", image_dir, num_threads=threads)
        os.replace(und / "images", tmp / "images")
        (tmp / "sparse").mkdir()
        model0 = tmp / "sparse" / "0"
        os.replace(und / "sparse", model0)
        # Re-write the undistorted model so the folder is binary whatever the undistorter
        # chose and every camera is PINHOLE: the undistorter leaves SIMPLE_PINHOLE cameras
        # as they are, and readers downstream get one model to handle.
        und_rec = pycolmap.Reconstruction(str(model0))
        _to_pinhole(und_rec)
        shutil.rmtree(model0)
        model0.mkdir()
        und_rec.write_binary(str(model0))
        shutil.rmtree(und)
        timings["undistort"] = time.perf_counter() - t0
        timings["total"] = time.perf_counter() - t_start

        result = SfmResult(root=out, model_dir=out / "sparse" / "0", image_dir=out / "images",
                           registered=tuple(registered), unregistered=tuple(unregistered),
                           num_models=len(models), num_points3d=int(num_points),
                           mean_reprojection_error_px=reproj, matcher=matcher,
                           timings_s={k: round(v, 3) for k, v in timings.items()})
        summary = result.to_json()
        summary["options"] = dataclasses.asdict(options)
        summary["num_threads_used"] = threads
        summary["pycolmap_version"] = pycolmap.__version__
        with open(tmp / Files.SFM, "w", encoding="utf-8") as f:
            json.dump(summary, f, indent=1)
        if out.exists():
            out.rmdir()  # empty, checked by _prepare_out
        os.replace(tmp, out)
        return result
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        pycolmap.logging.minloglevel = level


def undistort_masks(sfm_root: os.PathLike | str, mask_root: os.PathLike | str,
                    out_dir: os.PathLike | str) -> dict:
    """Undistort a dataset's masks (``mask_root/masks/<object>/<image stem>.*``, made for
    the original photos) with the same mapping COLMAP's undistorter applied to the images,
    so they line up with ``sfm_root/images``; nearest-neighbour sampling keeps 0 / 255.

    Each undistorted pixel centre is taken through the undistorted (PINHOLE) camera to a
    viewing ray and through the distorted camera back to the original image (COLMAP's
    half-pixel convention), where the mask is sampled. A mask at another size than the
    image SfM ran on is first resized (nearest) when its aspect matches; otherwise it is
    refused naming the file.

    Returns:
        ``{"masks": n written, "objects": [...], "resized": [...]}``; the masks go to
        ``out_dir/<object>/<image stem>.png``.
    """
    import cv2
    import numpy as np
    from cobgs.data.pycolmap_import import import_pycolmap

    pycolmap = import_pycolmap()

    from cobgs.data.scene import find_object_files

    root = Path(sfm_root)
    dist = pycolmap.Reconstruction(str(root / "distorted" / "sparse" / "0"))
    if all(c.model.name in ("SIMPLE_PINHOLE", "PINHOLE") for c in dist.cameras.values()):
        # no distortion: undistortion keeps every pixel where it is
        return {"masks": 0, "objects": [], "resized": [], "reason": "pinhole cameras: masks line up as they are"}
    und = pycolmap.Reconstruction(str(root / "sparse" / "0"))
    und_by_name = {im.name: im for im in und.images.values()}
    out, written, objects, resized = Path(out_dir), 0, set(), []
    for im in dist.images.values():
        stem = Path(im.name).stem
        files = find_object_files(mask_root, stem, "masks")
        if not files or im.name not in und_by_name:
            continue
        dc = dist.cameras[im.camera_id]
        uc = und.cameras[und_by_name[im.name].camera_id]
        ys, xs = np.mgrid[0:uc.height, 0:uc.width].astype(np.float64)
        pix = np.stack([xs.ravel() + 0.5, ys.ravel() + 0.5], axis=1)
        rays = uc.cam_from_img(pix)
        src = dc.img_from_cam(np.concatenate([rays, np.ones((len(rays), 1))], axis=1), False)
        map_x = (src[:, 0] - 0.5).reshape(uc.height, uc.width).astype(np.float32)
        map_y = (src[:, 1] - 0.5).reshape(uc.height, uc.width).astype(np.float32)
        for obj, f in files.items():
            m = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION)  # as stored (data.images)
            if m is None:
                raise DataError("unreadable mask", f)
            if m.shape != (dc.height, dc.width):
                h, w = m.shape
                if abs(w / h - dc.width / dc.height) > 0.01:
                    raise DataError(f"mask is {w}x{h}; the image SfM ran on is {dc.width}x{dc.height} "
                                    "(another aspect ratio: a mask must be made for its photo)", f)
                m = cv2.resize(m, (dc.width, dc.height), interpolation=cv2.INTER_NEAREST)
                resized.append(f"{obj}/{f.name}")
            u = cv2.remap(m, map_x, map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            (out / obj).mkdir(parents=True, exist_ok=True)
            if not cv2.imwrite(str(out / obj / f"{stem}.png"), np.where(u >= 128, 255, 0).astype(np.uint8)):
                raise DataError("could not write an undistorted mask", out / obj / f"{stem}.png")
            written += 1
            objects.add(obj)
    return {"masks": written, "objects": sorted(objects), "resized": sorted(resized)}


def _other_sizes(image_dir: Path, names: list, unregistered: list) -> str:
    """"; 0007.jpg is 640x480 where the others are 1008x756 (...)" for unregistered images of
    another size than most: the likely reason they did not register (another camera, a crop)."""
    from collections import Counter

    from cobgs.data.images import probe

    sizes = {}
    for n in names:
        try:
            sizes[n] = probe(Path(image_dir) / n)[:2]
        except DataError:
            continue
    if not sizes:
        return ""
    common, _ = Counter(sizes.values()).most_common(1)[0]
    odd = [n for n in unregistered if n in sizes and sizes[n] != common]
    if not odd:
        return ""
    shown = ", ".join(f"{n} is {sizes[n][0]}x{sizes[n][1]}" for n in odd[:5])
    return (f"; {shown} where the others are {common[0]}x{common[1]} (another camera or a crop: such a photo rarely "
            "matches the rest; remove it, or give it its own scene)")


def triangulate_known_poses(image_dir: os.PathLike | str, cameras: Dict[str, tuple],
                            work_dir: os.PathLike | str, options: SfmOptions = SfmOptions()) -> dict:
    """Sparse points of a posed scene without any: SIFT features and matches as in
    :func:`run_sfm`, then COLMAP's point triangulator with the given cameras held fixed
    (``pycolmap.triangulate_points``), so the points are in the scene's own frame.

    Args:
        image_dir: the images (read only).
        cameras: image name in ``image_dir`` -> ``(fx, fy, cx, cy, width, height, w2c)``:
            pinhole intrinsics at ``width`` x ``height`` (scaled to the image's actual
            size) and a 4x4 world-to-camera matrix (OpenCV axes).
        work_dir: an empty folder for the database (removed by the caller).
        options: extraction / matching options (camera model and device are not used).

    Returns:
        ``{"xyz": float [N, 3], "rgb": uint8 [N, 3], "points": N, "images": n,
        "reprojection_error_px": e, "mean_track_length": l}`` (N may be 0).
    """
    import numpy as np
    from cobgs.data.pycolmap_import import import_pycolmap

    pycolmap = import_pycolmap()
    from PIL import Image

    image_dir, work = Path(image_dir), Path(work_dir)
    names = sorted(cameras)
    if len(names) < 2:
        raise DataError(f"triangulation needs at least 2 posed images, got {len(names)}", image_dir)
    db = work / "database.db"
    threads = options.threads()
    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 0 if options.verbose else 1
    try:
        pycolmap.set_random_seed(options.seed)
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "PINHOLE"
        pycolmap.extract_features(db, image_dir, image_names=names, camera_mode=pycolmap.CameraMode.PER_IMAGE,
                                  reader_options=reader,
                                  extraction_options=_extraction_options(pycolmap, options, threads))
        pycolmap.match_exhaustive(db, matching_options=_matching_options(pycolmap, options, threads))
        database = pycolmap.Database.open(str(db))
        try:
            images = database.read_all_images()
            cams = {c.camera_id: c for c in database.read_all_cameras()}
            rigs, frames = database.read_all_rigs(), database.read_all_frames()
        finally:
            database.close()
        rec = pycolmap.Reconstruction()
        by_frame = {}
        for im in images:
            fx, fy, cx, cy, w, h, _ = cameras[im.name]
            with Image.open(image_dir / im.name) as pic:
                iw, ih = pic.size
            sx, sy = iw / w, ih / h
            cam = cams[im.camera_id]
            cam.model = pycolmap.CameraModelId.PINHOLE
            cam.width, cam.height = iw, ih
            cam.params = [fx * sx, fy * sy, cx * sx, cy * sy]
            by_frame[im.frame_id] = im
        for c in cams.values():
            rec.add_camera(c)
        for r in rigs:
            rec.add_rig(r)
        for f in frames:
            w2c = np.asarray(cameras[by_frame[f.frame_id].name][6], dtype=np.float64)
            f.rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[:3, :3]), w2c[:3, 3])
            rec.add_frame(f)
        for im in images:
            rec.add_image(im)
        for f in frames:
            rec.register_frame(f.frame_id)
        out = work / "triangulated"
        out.mkdir()
        tri = pycolmap.triangulate_points(rec, db, image_dir, out)
    finally:
        pycolmap.logging.minloglevel = level
    pts = list(tri.points3D.values())
    xyz = np.array([p.xyz for p in pts], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in pts], dtype=np.uint8).reshape(-1, 3)
    return {"xyz": xyz, "rgb": rgb, "points": len(pts), "images": len(names),
            "reprojection_error_px": float(tri.compute_mean_reprojection_error()) if pts else None,
            "mean_track_length": float(np.mean([p.track.length() for p in pts])) if pts else None}
