"""Benchmark: generate each synthetic preset, run pycolmap SfM on it, check the poses.

    python tests/benchmarks/bm_synthetic.py [--presets demo forward orbit] [--out DIR]

Prints, per preset: generation wall and CPU time, SfM registration count, SfM time per
step, mean reprojection error, and the SfM poses against the generator's ground truth
(camera-centre residual after a similarity alignment, relative to the spread of the
centres; worst relative rotation error). The machine is shared, so CPU time is printed
next to wall time: it is the steadier number.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from cobgs.data.synth.scene import PRESETS, generate_scene  # noqa: E402
from cobgs.data.sfm import run_sfm  # noqa: E402
from cobgs.configs import SfmOptions


def _pose_errors(scene: Path, model: Path):
    import pycolmap

    tf = json.loads((scene / "transforms.json").read_text())
    gt = {Path(f["file_path"]).name: np.asarray(f["transform_matrix"]) for f in tf["frames"]}
    rec = pycolmap.Reconstruction(str(model))
    imgs = sorted(rec.images.values(), key=lambda im: im.name)
    est = np.stack([im.projection_center() for im in imgs])
    ref = np.stack([gt[im.name][:3, 3] for im in imgs])
    ms, md = est.mean(0), ref.mean(0)
    u, d, vt = np.linalg.svd((ref - md).T @ (est - ms) / len(est))
    e = np.diag([1.0, 1.0, np.sign(np.linalg.det(u) * np.linalg.det(vt))])
    rot = u @ e @ vt
    s = np.trace(np.diag(d) @ e) / ((est - ms) ** 2).sum(1).mean()
    resid = np.linalg.norm(s * (est - ms) @ rot.T + md - ref, axis=1)
    spread = np.linalg.norm(ref - md, axis=1).mean()
    r_est = [im.cam_from_world().matrix()[:3, :3].T for im in imgs]
    r_gt = [gt[im.name][:3, :3] @ np.diag([1.0, -1.0, -1.0]) for im in imgs]
    worst = 0.0
    for i in range(1, len(imgs)):
        dr = (r_gt[0].T @ r_gt[i]).T @ (r_est[0].T @ r_est[i])
        worst = max(worst, float(np.degrees(np.arccos(np.clip((np.trace(dr) - 1) / 2, -1, 1)))))
    (cam,) = rec.cameras.values()
    return resid.max() / spread, worst, float(cam.params[0]) / tf["fl_x"] - 1.0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--presets", nargs="+", default=list(PRESETS), choices=list(PRESETS))
    ap.add_argument("--out", default=None, help="keep the scenes here (default: a temp folder)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--threads", type=int, default=0, help="SfM threads (0 = all cores)")
    args = ap.parse_args()
    root = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="bm_synth_"))
    rows = []
    try:
        for name in args.presets:
            scene = root / f"synth_{name}"
            t0, c0 = time.perf_counter(), time.process_time()
            generate_scene(scene, name, args.seed, overwrite=True, progress=False,
                           workers=args.workers)
            gen_wall, gen_cpu = time.perf_counter() - t0, time.process_time() - c0
            sfm_dir = root / f"sfm_{name}"
            shutil.rmtree(sfm_dir, ignore_errors=True)
            res = run_sfm(scene / "images", sfm_dir, SfmOptions(
                camera_model="SIMPLE_PINHOLE", num_threads=args.threads, min_registered_fraction=0.0))
            n = len(res.registered) + len(res.unregistered)
            centre, rot, focal = _pose_errors(scene, res.model_dir)
            p = PRESETS[name]
            rows.append((name, f"{p.width_px}x{p.height_px}", n, f"{gen_wall:.1f}", f"{gen_cpu:.1f}",
                         f"{len(res.registered)}/{n}", f"{res.timings_s['total']:.1f}",
                         f"{res.mean_reprojection_error_px:.3f}", res.num_points3d,
                         f"{100 * centre:.2f}%", f"{rot:.3f}", f"{100 * focal:+.2f}%"))
            print(f"{name}: sfm timings {res.timings_s}", flush=True)
    finally:
        if not args.out:
            shutil.rmtree(root, ignore_errors=True)
    head = ("preset", "size", "views", "gen wall s", "gen cpu s", "registered", "sfm s",
            "reproj px", "points", "centre err", "rot err deg", "focal err")
    widths = [max(len(str(r[i])) for r in rows + [head]) for i in range(len(head))]
    for r in [head] + rows:
        print("  ".join(str(v).rjust(w) for v, w in zip(r, widths)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
