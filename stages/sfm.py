"""Stage ``sfm``: camera poses with pycolmap (cobgs.data.sfm), or a recorded skip.

``mode = "auto"`` runs SfM only when the dataset has no poses; ``"always"`` runs it anyway
(the demo reconstructs its synthetic views, as a user's capture would be); ``"never"``
skips it. The matcher follows :class:`cobgs.data.sfm.SfmOptions` ("auto": exhaustive up to
``exhaustive_max_images`` images, sequential above — ordered captures). Too few
registered images fail the task with a message naming the images that did not register.

Output ``poses``: ``sfm.json`` (``{"ran": bool, "reason", ...cobgs.data.sfm summary}``) and,
when SfM ran, ``images/`` (undistorted, PINHOLE) and ``sparse/0/``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

from cobgs.configs import Files, SfmOptions, check_params
from pipeline import Resources, Stage

from ._common import StageInputError, load_scene, read_json, read_spec, spec_path, write_json


@dataclass(frozen=True)
class SfmParams:
    """Attributes:
        mode: "auto" (only without poses), "always", "never".
        options: the SfM options.
        triangulate: a posed scene without 3D points (a transforms.json without a point
            cloud, LLFF poses_bounds, NeX's copy) gets them by COLMAP's point triangulator
            with its own poses held fixed, instead of training from a random box (which
            holds only empty space near the cameras of a forward-facing capture); the
            random box stays where triangulation finds nothing. sfm.json says which.
    """

    mode: str = "auto"
    options: SfmOptions = field(default_factory=SfmOptions)
    triangulate: bool = True

    CHOICES: ClassVar[dict] = {"mode": ("auto", "always", "never")}

    def __post_init__(self) -> None:
        check_params(self)
        if self.mode not in ("auto", "always", "never"):
            raise ValueError(f"mode must be 'auto', 'always' or 'never', got {self.mode!r}")
        if self.options.device != SfmOptions.device:
            raise ValueError("sfm.options.device is the workflow's device (settings.device, "
                             f"--set device=cuda), not a param; got {self.options.device!r}")


def _run(ctx, inputs):
    from cobgs.data.sfm import run_sfm

    p: SfmParams = ctx.params
    spec = read_spec(inputs["dataset"])
    has_poses = bool(spec.has_poses)
    run = p.mode == "always" or (p.mode == "auto" and not has_poses)
    if not run:
        reason = ("mode 'never'" if p.mode == "never" else "the dataset has poses")
        if not has_poses:
            raise StageInputError(f"scene {spec['scene']!r} has no poses and sfm.mode is 'never'")
        info = {"ran": False, "reason": reason}
        if p.triangulate:
            info["initial_points"] = _triangulate(ctx, p, spec, inputs)
        write_json(ctx.out_dir / Files.SFM, info)
        ctx.log.info("SfM skipped: %s", reason)
        ctx.note(ran=False, reason=reason, initial_points=(info.get("initial_points") or {}).get("source"))
        return {"poses": ctx.out_dir}
    images = spec.images
    if not images:
        raise StageInputError(f"dataset kind {spec['kind']!r} has no image folder to run SfM on "
                              "(set sfm.mode = 'auto' to use its own poses)")
    image_dir = spec_path(Path(inputs["dataset"]), images["dir"])
    device = "cuda" if ctx.device.startswith("cuda") else "cpu"
    if device == "cuda":
        from cobgs.data.pycolmap_import import import_pycolmap

        pycolmap = import_pycolmap()

        if not pycolmap.has_cuda:  # PyPI's pycolmap wheels are CPU builds
            ctx.log.info("pycolmap %s has no CUDA: SIFT extraction and matching run on the CPU "
                         "(the rest of the workflow stays on %s)", pycolmap.__version__, ctx.device)
            device = "cpu"
    opts = dataclasses.replace(p.options, device=device)
    ctx.log.info("SfM on %d images of %s (%s matcher, %s)", len(images["names"]), image_dir,
                 opts.matcher, opts.camera_model)
    res = run_sfm(image_dir, ctx.scratch_dir / "sfm", opts, image_names=images["names"])
    # The result folder is built in scratch (run_sfm renames its own temporary folder into
    # place); move its parts into the artifact.
    # Masks made for the original photos, undistorted like the images (nearest), so they
    # line up with them; readers then take the masks from this artifact.
    mask_info = None
    src = spec.reader.get("path")
    data_root = spec_path(Path(inputs["dataset"]), src) if src is not None else None
    if data_root is not None and (data_root / "masks").is_dir():
        from cobgs.data.sfm import undistort_masks

        mask_info = undistort_masks(res.root, data_root, ctx.out_dir / "masks")
        if mask_info["masks"]:
            ctx.log.info("undistorted %d masks of %s like the images%s", mask_info["masks"],
                         mask_info["objects"], f" (resized first: {len(mask_info['resized'])})"
                         if mask_info["resized"] else "")
    for part in (Files.SFM_IMAGES, Files.SFM_MODEL.split("/")[0], Files.SFM):
        (res.root / part).rename(ctx.out_dir / part)
    summary = read_json(ctx.out_dir / Files.SFM)
    # Paths inside the artifact, relative (the scratch folder SfM ran in is gone).
    summary.update(root=".", model_dir=Files.SFM_MODEL, image_dir=Files.SFM_IMAGES)
    summary.update(ran=True, reason=f"mode {p.mode!r}" + ("" if has_poses else ", the dataset has no poses"))
    summary.pop("timings_s", None)  # in the manifest (ctx.note below): same bytes on a recompute
    if mask_info is not None:
        summary["undistorted_masks"] = mask_info
    write_json(ctx.out_dir / Files.SFM, summary)
    ctx.note(ran=True, registered=len(res.registered), unregistered=len(res.unregistered),
             points3d=res.num_points3d, reprojection_error_px=res.mean_reprojection_error_px,
             matcher=res.matcher, timings_s=res.timings_s)
    return {"poses": ctx.out_dir}


def _triangulate(ctx, p: SfmParams, spec: dict, inputs) -> dict:
    """Initial points of a posed scene that has none (see ``SfmParams.triangulate``):
    ``points.npz`` in the artifact, and what was done."""
    scene = load_scene(inputs["dataset"], None)
    if scene.points is not None and len(scene.points) > 0:
        return {"source": "the dataset's", "points": int(len(scene.points))}
    import shutil

    import numpy as np

    from cobgs.data.sfm import triangulate_known_poses

    images = spec.images
    cams = {}
    if images:
        image_dir = spec_path(Path(inputs["dataset"]), images["dir"])
        names = images["names"]
        views = {v.name: v for v in scene.views}
        pairs = [(n, views.get(Path(n).stem)) for n in names]
    else:
        # A posed layout without one image folder (NeRF's train/ and test/ with
        # transforms_*.json): the training views' own files, when they share a folder.
        files = [(v, Path(v.path)) for v in scene.train if v.path is not None]
        dirs = {f.parent for _, f in files}
        if len(dirs) != 1:
            return {"source": "random box", "why": "the training views' images are not in one folder "
                                                   f"({len(dirs)} folders)"}
        image_dir = dirs.pop()
        pairs = [(f.name, v) for v, f in files]
    for n, v in pairs:
        if v is not None:
            c = v.camera
            cams[n] = (c.fx, c.fy, c.cx, c.cy, c.width, c.height, c.viewmat.double().cpu().numpy())
    if len(cams) < 2:  # nothing to triangulate between
        ctx.log.warning("%d posed image(s) match the views: training starts from a random box", len(cams))
        return {"source": "random box", "why": f"{len(cams)} posed image(s) match the views; "
                                                "triangulation needs 2", "images": len(cams)}
    work = ctx.scratch_dir / "triangulate"
    work.mkdir(parents=True)
    ctx.log.info("triangulating %d posed images (%s) with their known poses", len(cams), image_dir)
    try:
        res = triangulate_known_poses(image_dir, cams, work, p.options)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    if res["points"] == 0:
        ctx.log.warning("triangulation found no point: training starts from a random box")
        return {"source": "random box", "why": "triangulation with the known poses found no point",
                "images": res["images"]}
    np.savez_compressed(ctx.out_dir / Files.SFM_POINTS, xyz=res["xyz"].astype(np.float32), rgb=res["rgb"])
    ctx.log.info("triangulated %d points (reprojection error %.2f px)", res["points"], res["reprojection_error_px"])
    return {"source": "triangulated with the known poses", "points": res["points"], "images": res["images"],
            "reprojection_error_px": round(res["reprojection_error_px"], 4),
            "mean_track_length": round(res["mean_track_length"], 3)}


def _check(p: SfmParams) -> None:
    """The library's checks of the SfM options (SfmOptions, and the camera model against
    pycolmap's list), before any task runs."""
    from cobgs.data.pycolmap_import import import_pycolmap

    pycolmap = import_pycolmap()

    from cobgs.data.sfm import check_camera

    check_camera(pycolmap, p.options)


STAGE = Stage(
    name="sfm", version=4, run=_run, inputs=("dataset",), outputs=("poses",), params=SfmParams,
    level=("scene",), uses_device=True, resources=Resources(cpus=2),
    description="pycolmap SfM (skipped when the dataset has poses, unless mode = 'always')", check=_check,
)
