"""Bring your own trained 3DGS: a scene trained elsewhere, checked against its data.

COB-GS is a post-processing of a trained 3DGS scene; users often have one already. Two
sources are read:

* **An output folder of the original 3DGS code** (``train.py -m OUT``)::

      OUT/point_cloud/iteration_<N>/point_cloud.ply   the Gaussians (highest N unless one
                                                      is named)
      OUT/cameras.json                                the training cameras (camera-to-world
                                                      position and rotation, fx, fy, size)
      OUT/cfg_args                                    the arguments (sh_degree, source_path, ...)
      OUT/chkpnt<N>.pth                               optional: (model + optimizer state,
                                                      iteration), from --checkpoint_iterations

  When ``chkpnt<N>.pth`` of the same iteration exists, its Adam state becomes the texture
  stages' starting moments (the released COB-GS continues that optimizer state). It is
  read with ``torch.load(..., weights_only=True)``: tensors, numbers, lists and dicts only,
  never arbitrary pickled objects.
* **Any standard 3DGS PLY** (gsplat, nerfstudio's splatfacto export, ...).

:func:`check_against_scene` refuses a scene that does not belong to the data: Gaussians
that no training camera sees (another world frame, another scene), cameras.json cameras
away from the scene's, an SH degree that disagrees with ``cfg_args``. Everything read and
decided is returned for the manifest.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from cobgs.data.trained_layout import find_trained_ply, read_cameras_json, read_cfg_args, saved_iterations
from cobgs.errors import DataError
from cobgs.gaussians.model import GaussianModel

__all__ = ["ImportedScene", "read_trained", "read_3dgs_output", "read_trained_ply",
           "read_3dgs_checkpoint_moments", "check_against_scene"]

# The original 3DGS optimizer's group names -> the tensors of GaussianModel.
_GROUPS = {"xyz": "means", "f_dc": "sh0", "f_rest": "shN", "opacity": "opacity_logits",
           "scaling": "log_scales", "rotation": "quats"}


@dataclass
class ImportedScene:
    """A trained scene read from elsewhere.

    Attributes:
        model: the Gaussians.
        moments: Adam moments in :mod:`cobgs.train.adam_moments`'s layout, or None.
        source: what was read (for the manifest): kind, files, iteration, SH degree, ...
        cameras: ``{image name stem: (camera centre [3], fx, width)}`` from cameras.json.
        notes: decisions a user should know about.
    """

    model: GaussianModel
    moments: Optional[dict] = None
    source: dict = field(default_factory=dict)
    cameras: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)


def read_trained(path: Path, iteration: int = 0) -> ImportedScene:
    """A 3DGS output folder (a folder holding ``point_cloud/``) or a PLY file."""
    path = Path(path)
    if path.is_dir():
        return read_3dgs_output(path, iteration)
    find_trained_ply(path, iteration)  # a missing path or an iteration of a bare PLY: named
    return read_trained_ply(path)


def read_trained_ply(path: Path) -> ImportedScene:
    from cobgs.gaussians.ply import load_ply

    model = load_ply(path)
    return ImportedScene(model, source={"kind": "ply", "ply": str(path), "num_gaussians": len(model),
                                        "sh_degree": model.sh_degree})


def read_3dgs_output(folder: Path, iteration: int = 0) -> ImportedScene:
    """The original 3DGS code's output folder (see the module docstring)."""
    from cobgs.gaussians.ply import load_ply

    folder = Path(folder)
    ply, it = find_trained_ply(folder, iteration)
    model = load_ply(ply)
    src = {"kind": "3dgs_output", "folder": str(folder), "iteration": it, "ply": str(ply),
           "saved_iterations": sorted(saved_iterations(folder)), "num_gaussians": len(model),
           "sh_degree": model.sh_degree}
    notes = []
    cfg = read_cfg_args(folder / "cfg_args")
    if cfg:
        src["cfg_args"] = cfg
        if "sh_degree" in cfg and cfg["sh_degree"] != model.sh_degree:
            raise DataError(f"cfg_args says sh_degree={cfg['sh_degree']}, but {ply.name} of "
                            f"iteration {it} holds degree {model.sh_degree}", folder / "cfg_args")
    cameras = {}
    if (folder / "cameras.json").is_file():
        cameras = {k: (np.asarray(p, np.float64), fx, w)
                   for k, (p, fx, w) in read_cameras_json(folder / "cameras.json").items()}
    if cameras:
        src["cameras_json"] = str(folder / "cameras.json")
    ck = folder / f"chkpnt{it}.pth"
    moments = None
    if ck.is_file():
        moments = read_3dgs_checkpoint_moments(ck, model)
        src["checkpoint"] = str(ck)
        notes.append(f"Adam moments of {ck.name} continue in the texture stages")
    else:
        others = sorted(p.name for p in folder.glob("chkpnt*.pth"))
        notes.append(f"no chkpnt{it}.pth beside iteration {it}" + (f" (found {others})" if others else "")
                     + ": the texture stages start from zero Adam moments")
    return ImportedScene(model, moments, src, cameras, notes)


def read_3dgs_checkpoint_moments(path: Path, model: GaussianModel) -> dict:
    """The Adam moments of an original-3DGS checkpoint ``(capture tuple, iteration)``, in
    the layout of :mod:`cobgs.train.adam_moments`, checked against ``model`` (the PLY of the same
    iteration).

    Raises:
        DataError: unreadable or unsafe file (anything ``weights_only`` refuses), not a 3DGS
            checkpoint, or one whose Gaussians are not the PLY's.
    """
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises UnpicklingError, RuntimeError, ...
        raise DataError(f"cannot read the checkpoint with torch.load(weights_only=True) (only "
                        f"tensors, numbers, lists and dicts are accepted): {e}", path) from e
    try:
        capture, _ = data
        xyz = capture[1]
        opt_state = capture[10]
        groups = opt_state["param_groups"]
        state = opt_state["state"]
    except (TypeError, ValueError, IndexError, KeyError) as e:
        raise DataError("not an original-3DGS checkpoint ((active_sh_degree, xyz, f_dc, f_rest, "
                        "scaling, rotation, opacity, max_radii, grad_accum, denom, optimizer "
                        f"state, spatial_lr_scale), iteration): {e!r}", path) from e
    if not isinstance(xyz, torch.Tensor) or tuple(xyz.shape) != (len(model), 3) or \
            not torch.allclose(xyz.float(), model.means.detach().float(), atol=1e-5):
        raise DataError(f"the checkpoint's Gaussians are not those of the PLY it is read with "
                        f"({tuple(getattr(xyz, 'shape', ()))} vs {len(model)} Gaussians, or other "
                        f"positions): checkpoint and point_cloud of different iterations?", path)
    shapes = {name: model.data[name].shape for name in _GROUPS.values()}
    out = {}
    try:
        for g in groups:
            name = _GROUPS.get(g.get("name"))
            if name is None:
                continue
            st = state.get(g["params"][0]) if g.get("params") else None
            if not st:
                continue
            entry = {}
            for k in ("exp_avg", "exp_avg_sq"):
                t = torch.as_tensor(st[k]).float()
                if t.numel() != int(np.prod(shapes[name])):
                    raise DataError(f"optimizer group {g.get('name')!r}: {k} has {t.numel()} "
                                    f"values, the PLY's {name} {int(np.prod(shapes[name]))}", path)
                if not torch.isfinite(t).all():
                    raise DataError(f"optimizer group {g.get('name')!r}: {k} has "
                                    f"{int((~torch.isfinite(t)).sum())} non-finite values", path)
                entry[k] = t.reshape(shapes[name]).contiguous()
            entry["step"] = torch.as_tensor(st.get("step", 0)).float().reshape(())
            out[name] = entry
    except (AttributeError, TypeError, ValueError, IndexError, KeyError, RuntimeError) as e:
        raise DataError(f"the optimizer state is not Adam state as the 3DGS code saves it "
                        f"(param_groups with a name and params; state with exp_avg, exp_avg_sq, "
                        f"step): {e!r}", path) from e
    missing = sorted(set(_GROUPS.values()) - set(out))
    if missing:
        raise DataError(f"the checkpoint's optimizer has no state for {missing}", path)
    return out


def check_against_scene(imported: ImportedScene, scene, min_visible: float = 0.5) -> dict:
    """Refuse a trained scene that does not belong to ``scene`` (its training views);
    returns what was measured.

    Raises:
        DataError: fewer than ``min_visible`` of the Gaussians lie in front of and project
            into some training camera, or (when the scene has SfM points) a sample of them
            lies away from those points — another world frame or another scene, the PLY is
            named; or cameras.json's cameras sit elsewhere than the scene's (named).
    """
    means = imported.model.means.detach().double().cpu()
    seen = torch.zeros(len(means), dtype=torch.bool)
    for v in scene.train:
        uv, z = v.camera.to(torch.device("cpu")).project(means.float())
        uv, z = uv.double(), z.double()
        seen |= (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < v.camera.width) & (uv[:, 1] >= 0) & \
            (uv[:, 1] < v.camera.height)
    frac = float(seen.double().mean()) if len(means) else 0.0
    where = imported.source.get("ply") or imported.source.get("folder")
    if frac < min_visible:
        raise DataError(f"only {frac:.1%} of its {len(means)} Gaussians lie inside some training "
                        f"camera's view of {scene.source or 'the scene'} (at least "
                        f"{min_visible:.0%} expected): it does not belong to this scene, or is in "
                        f"another world frame (check that it was trained on the same COLMAP model)",
                        where)
    out = {"visible_fraction": frac}
    if scene.points is not None and len(scene.points) >= 10:
        # Against the scene's SfM points: a sample of Gaussians must lie among them.
        pts = scene.points.detach().double().cpu()
        diag = float((pts.max(0).values - pts.min(0).values).norm())
        g = torch.Generator().manual_seed(0)
        sample = means[torch.randperm(len(means), generator=g)[:2000]]
        nearest = torch.cat([torch.cdist(c, pts).min(1).values for c in sample.split(256)])
        med = float(nearest.median()) if len(nearest) else 0.0
        out["median_distance_to_sfm_points_of_diagonal"] = med / max(diag, 1e-12)
        if med > 0.1 * diag:
            raise DataError(f"its Gaussians lie away from the scene's SfM points (median distance "
                            f"{med:.3g}, {med / max(diag, 1e-12):.1%} of the points' extent): it "
                            f"does not belong to this scene, or is in another world frame", where)
    if imported.cameras:
        extent = max(float(scene.extent), 1e-9)
        worst, matched = 0.0, 0
        for v in scene.train + scene.test:
            cam = imported.cameras.get(v.name)
            if cam is None:
                continue
            matched += 1
            d = float(np.linalg.norm(cam[0] - v.camera.center.detach().double().cpu().numpy()))
            worst = max(worst, d / extent)
            ratio_json, ratio_scene = cam[1] / cam[2], float(v.camera.fx) / float(v.camera.width)
            if abs(ratio_json - ratio_scene) > 0.01 * ratio_scene:
                raise DataError(f"camera {v.name!r}: fx / width {ratio_json:.4f} in cameras.json, "
                                f"{ratio_scene:.4f} in the scene (another calibration?)",
                                imported.source["cameras_json"])
        if matched == 0:
            raise DataError("no camera of cameras.json names a view of the scene (img_name)",
                            imported.source["cameras_json"])
        if worst > 1e-3:
            raise DataError(f"camera centres in cameras.json differ from the scene's by up to "
                            f"{worst:.2%} of the scene extent: trained on other poses or "
                            f"another world frame", imported.source["cameras_json"])
        out.update(cameras_matched=matched, camera_offset_of_extent=worst)
    out.update(degenerate_gaussians(imported.model, float(scene.extent)))
    return out


#: A Gaussian whose largest scale exceeds this many scene extents covers the whole scene.
HUGE_SCALE_OF_EXTENT = 100.0


def degenerate_gaussians(model: GaussianModel, extent: float) -> dict:
    """Fractions of Gaussians that cannot render as the scene trained them: a rotation of
    (near) zero norm (no orientation: normalising it gives NaN), a largest scale over
    :data:`HUGE_SCALE_OF_EXTENT` scene extents (``exp(80)``: a Gaussian over everything), or
    a non-finite value. ``warning`` says it in words when any is found ("" otherwise): a PLY
    of such Gaussians imports and runs to the end with an IoU of 0."""
    n = len(model)
    if n == 0:
        return {"degenerate": {}, "warning": ""}
    q = model.quats.detach().double().cpu()
    ls = model.log_scales.detach().double().cpu()
    zero_rot = q.norm(dim=1) < 1e-8
    huge = ls.max(dim=1).values > math.log(HUGE_SCALE_OF_EXTENT * max(extent, 1e-9))
    bad = ~torch.isfinite(torch.cat([model.data[k].detach().reshape(n, -1).double().cpu() for k in
                                     ("means", "log_scales", "quats", "opacity_logits", "sh0")], 1)).all(1)
    fr = {"zero_rotation": float(zero_rot.double().mean()), "huge_scale": float(huge.double().mean()),
          "non_finite": float(bad.double().mean())}
    words = {"zero_rotation": "a zero rotation (quaternion of norm 0)",
             "huge_scale": f"a scale over {HUGE_SCALE_OF_EXTENT:g} scene extents",
             "non_finite": "a non-finite value (nan / inf)"}
    found = [f"{v:.1%} have {words[k]}" for k, v in fr.items() if v > 0]
    warning = ""
    if found:
        warning = (f"{'; '.join(found)} of its {n} Gaussians: they render as nothing or as everything, so "
                   "the segmentation will be wrong (was the PLY written with another convention: "
                   "activated scales, another quaternion order?)")
    return {"degenerate": fr, "warning": warning}
