"""Small scenes in the published NVOS and LERF-mask layouts, made from a synthetic scene.

The synthetic generator knows the exact cameras and masks, so a scene written in another
layout keeps an exact ground truth: the protocols can then run end to end through the
pipeline and be checked against known answers.

* :func:`to_nvos` — an LLFF scene (``poses_bounds.npy`` + ``images_2/`` + ``masks/``) and
  an NVOS labels folder for one task (target = a held-out view, its GT mask at the
  "full" resolution, 2x the training images; scribbles at 1/4 of that).
* :func:`to_lerf_mask` — a COLMAP text model + ``images/`` + ``images_train/`` +
  ``test_mask/<idx>/<prompt>.png`` (+ ``masks/`` so the masks stage can read files).
* :func:`nvos_published` / :func:`lerf_mask_published` — every task / prompt of the two
  benchmarks with the published scene, view and prompt names, so ``workflows/nvos.toml``
  and ``workflows/lerf_mask.toml`` run unchanged on them
  (tests/benchmarks/bm_protocol_workflows.py).
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import cv2
import numpy as np

GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def _frames(scene: Path):
    tf = json.loads((scene / "transforms.json").read_text())
    out = []
    for f in tf["frames"]:
        c2w = np.asarray(f["transform_matrix"], np.float64) @ GL_TO_CV  # OpenCV axes
        out.append((Path(f["file_path"]).stem, scene / f["file_path"], c2w, f))
    return out


def published_names(target: str, reference: str, n: int) -> list[str]:
    """``n`` distinct view names in the style of ``target`` (IMG_4027, DJI_20200223_163024_597),
    sorted, containing ``target`` and ``reference``: the fillers count up the last number of
    the target's name, so sorting the names keeps them in capture order."""
    m = re.fullmatch(r"(.*?)(\d+)", target)
    if m is None:
        raise ValueError(f"target {target!r} does not end in a number")
    head, digits = m.groups()
    names, k = {target, reference}, 1
    while len(names) < n:
        names.add(f"{head}{int(digits) + k:0{len(digits)}d}")
        k += 1
    return sorted(names)


def to_nvos(scene: Path, out: Path, task: str, obj: str, target: str, reference: str,
            layout: str = "llff", factor: int = 2) -> tuple[Path, Path]:
    """Write ``out/llff`` and ``out/labels`` for one task; returns (scene folder, labels
    folder). The synthetic views keep their names; see :func:`write_llff` for ``layout``."""
    llff, labels = out / "llff", out / "labels"
    write_llff(scene, llff, layout, {obj: llff / "released_masks"}, factor=factor)
    write_nvos_labels(scene, labels, task, obj, target, reference, factor=factor)
    return llff, labels


def write_llff(scene: Path, llff: Path, layout: str, released: dict[str, Path],
               names: dict[str, str] | None = None, factor: int = 2) -> Path:
    """Write the synthetic ``scene`` as an LLFF scene folder whose "full" resolution is
    ``factor`` x the synthetic images, and ``images_<factor>/`` the synthetic images.

    ``layout``: "llff" (``poses_bounds.npy`` + ``images_<factor>/`` named like the views);
    "nerf_llff_data" (the copy COB-GS, SAGA and FlashSplat evaluate on: COLMAP
    ``sparse/0`` with a SIMPLE_RADIAL camera over full-size ``images/<view>.JPG``, and
    ``images_<factor>/image000.png`` ... in sorted order); "nex" (NeX's ``*_undistort``: a
    14-column ``poses_bounds.npy`` + ``hwf_cxcy.npy``, full-size ``images/``, and
    ``images_<factor>/image000.png`` ...). ``names`` renames views (synthetic stem ->
    published name); ``released`` maps objects to folders that get the object's mask of
    every view at the full size, JPEG-compressed and named ``<view>.JPG``, as COB-GS
    releases its NVOS masks.
    """
    names = names or {}
    (llff / f"images_{factor}").mkdir(parents=True)
    frames = sorted(_frames(scene), key=lambda fr: names.get(fr[0], fr[0]))
    rows, lines = [], []
    f0 = frames[0][3]
    k = float(factor)
    for i, (stem, img, c2w, f) in enumerate(frames):
        name = names.get(stem, stem)
        renamed = layout in ("nerf_llff_data", "nex")
        # nerf_llff_data names its downscaled DJI images (horns, trex) after the views
        small = f"image{i:03d}.png" if renamed and not name.startswith("DJI_") else f"{name}.png"
        shutil.copy(img, llff / f"images_{factor}" / small)
        big = cv2.resize(cv2.imread(str(img)), None, fx=k, fy=k, interpolation=cv2.INTER_LINEAR)
        if renamed:
            (llff / "images").mkdir(exist_ok=True)
            cv2.imwrite(str(llff / "images" / f"{name}.JPG"), big)
        for obj, folder in released.items():
            folder.mkdir(parents=True, exist_ok=True)
            m = cv2.imread(str(scene / "masks" / obj / f"{stem}.png"), cv2.IMREAD_GRAYSCALE)
            cv2.imwrite(str(folder / f"{name}.JPG"),
                        cv2.resize(m, None, fx=k, fy=k, interpolation=cv2.INTER_NEAREST))
        # LLFF columns: down, right, backward (then translation, then [h, w, focal] at full res).
        rot = np.stack([c2w[:3, 1], c2w[:3, 0], -c2w[:3, 2]], 1)
        if layout == "nex":
            rows.append(np.concatenate([np.column_stack([rot, c2w[:3, 3]]).ravel(), [0.5, 20.0]]))
        else:
            hwf = np.array([k * f["h"], k * f["w"], k * f["fl_x"]])
            rows.append(np.concatenate([np.column_stack([rot, c2w[:3, 3], hwf]).ravel(), [0.5, 20.0]]))
        w2c = np.linalg.inv(c2w)
        q, t = _quat_wxyz(w2c[:3, :3]), w2c[:3, 3]
        lines.append(f"{i + 1} {' '.join(repr(float(v)) for v in q)} {' '.join(repr(float(v)) for v in t)} 1 {name}.JPG\n\n")
    if layout == "nerf_llff_data":
        model = llff / "sparse" / "0"
        model.mkdir(parents=True)
        # SIMPLE_RADIAL at the full size (the images are pinhole renders: k1 tiny), as COLMAP
        # leaves it; the reference methods read it as a pinhole.
        (model / "cameras.txt").write_text(
            f"1 SIMPLE_RADIAL {k * f0['w']:g} {k * f0['h']:g} {k * f0['fl_x']} {k * f0['cx']} "
            f"{k * f0['cy']} 0.0001\n")
        (model / "images.txt").write_text("".join(lines))
        _write_points3d(model / "points3D.txt", scene)
    else:
        np.save(llff / "poses_bounds.npy", np.stack(rows))
        if layout == "nex":
            np.save(llff / "hwf_cxcy.npy", k * np.array(
                [[f0["h"]], [f0["w"]], [f0["fl_x"]], [f0["fl_y"]], [f0["cx"]], [f0["cy"]]]))
    for src in sorted((scene / "masks").iterdir()):
        (llff / "masks" / src.name).mkdir(parents=True)
        for f in src.iterdir():
            shutil.copy(f, llff / "masks" / src.name / (names.get(f.stem, f.stem) + f.suffix))
    return llff


def _write_points3d(path: Path, scene: Path) -> None:
    """The sparse points a COLMAP model carries (here: the surfaces the cameras see)."""
    xyz, rgb = surface_points(scene)
    path.write_text("".join(f"{i + 1} {x!r} {y!r} {z!r} {r} {g} {b} 0.5\n"
                            for i, ((x, y, z), (r, g, b)) in enumerate(zip(xyz.tolist(), rgb.tolist()))))


def surface_points(scene: Path, step: int = 8, limit: int = 4000) -> tuple[np.ndarray, np.ndarray]:
    """Points on the surfaces a synthetic scene's cameras see ([N, 3] float, [N, 3] uint8
    colours from the images): rays through every ``step``-th pixel of every view, cast
    against the scene the generator rebuilds from ``scene.json``; at most ``limit``."""
    from cobgs.data.synth.render import make_caster
    from cobgs.data.synth.scene import build_scene

    meta = json.loads((scene / "scene.json").read_text())
    w, h = meta["image_size"]
    _, synth, cams = build_scene(meta["preset"], meta["seed"], num_views=meta["num_views"],
                                 width_px=w, height_px=h)
    caster = make_caster(synth)
    stems = sorted(p.stem for p in (scene / "images").iterdir())
    xyz, rgb = [], []
    for cam, stem in zip(cams, stems):
        img = cv2.imread(str(scene / "images" / f"{stem}.png"))[:, :, ::-1]
        v, u = np.mgrid[step // 2:h:step, step // 2:w:step]
        u, v = u.ravel(), v.ravel()
        c2w = cam.c2w_array
        d = np.stack([(u + 0.5 - cam.cx) / cam.fx, (v + 0.5 - cam.cy) / cam.fy, np.ones(len(u))], 1) @ c2w[:3, :3].T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        t, which = caster.first_hit(c2w[:3, 3], d)
        hit = (which >= 0) & np.isfinite(t)
        xyz.append(c2w[:3, 3] + t[hit, None] * d[hit])
        rgb.append(img[v[hit], u[hit]])
    xyz, rgb = np.concatenate(xyz), np.concatenate(rgb)
    keep = np.random.default_rng(0).permutation(len(xyz))[:limit]
    return xyz[keep], rgb[keep]


def write_nvos_labels(scene: Path, labels: Path, task: str, obj: str, target: str,
                      reference: str, names: dict[str, str] | None = None, factor: int = 2) -> Path:
    """Add ``task`` to an NVOS labels folder: ``masks/<task>/<target>.JPG`` +
    ``<target>_mask.png`` at the full size (``factor`` x the synthetic images),
    ``reference_image/<task>/<reference>.JPG``, and ``scribbles/<task>/pos_0.png`` /
    ``neg_0.png`` at 1/4 of the full size. ``target`` / ``reference`` are synthetic view
    stems; ``names`` maps them to the published names the files carry."""
    names = names or {}

    def up(a):
        return cv2.resize(a, None, fx=factor, fy=factor, interpolation=cv2.INTER_NEAREST)

    img_t = cv2.imread(str(scene / "images" / f"{target}.png"))
    img_r = cv2.imread(str(scene / "images" / f"{reference}.png"))
    gt = cv2.imread(str(scene / "masks" / obj / f"{target}.png"), cv2.IMREAD_GRAYSCALE)
    t_name, r_name = names.get(target, target), names.get(reference, reference)
    for sub in ("masks", "reference_image", "scribbles"):
        (labels / sub / task).mkdir(parents=True)
    cv2.imwrite(str(labels / "masks" / task / f"{t_name}.JPG"), up(img_t))
    cv2.imwrite(str(labels / "masks" / task / f"{t_name}_mask.png"), up(gt))
    cv2.imwrite(str(labels / "reference_image" / task / f"{r_name}.JPG"), up(img_r))
    # Scribbles at 1/4 of the full size: a stroke through the object's centre and one on the
    # background.
    ref = up(cv2.imread(str(scene / "masks" / obj / f"{reference}.png"), cv2.IMREAD_GRAYSCALE))
    small = cv2.resize(ref, None, fx=0.25, fy=0.25, interpolation=cv2.INTER_NEAREST)
    ys, xs = np.nonzero(small)
    pos = np.zeros_like(small)
    cy, cx = int(ys.mean()), int(xs.mean())
    pos[cy, max(0, cx - 2): cx + 3] = 255
    neg = np.zeros_like(small)
    neg[1, 1:6] = 255
    cv2.imwrite(str(labels / "scribbles" / task / "pos_0.png"), pos)
    cv2.imwrite(str(labels / "scribbles" / task / "neg_0.png"), neg)
    return labels


def _quat_wxyz(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix (Shepperd's method)."""
    t = np.trace(r)
    if t > 0:
        s = 2.0 * np.sqrt(t + 1.0)
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(r)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + r[i, i] - r[j, j] - r[k, k])
        q = [0.0] * 4
        q[0] = (r[k, j] - r[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (r[j, i] + r[i, j]) / s
        q[1 + k] = (r[k, i] + r[i, k]) / s
    q = np.asarray(q)
    return q / np.linalg.norm(q)


def to_lerf_mask(scene: Path, out: Path, prompts: dict[str, str], test_every: int = 4) -> tuple[Path, list[str]]:
    """Write a LERF-mask scene; ``prompts`` maps prompt -> synthetic object. Returns
    (folder, test view stems in protocol order)."""
    frames = _frames(scene)
    (out / "images").mkdir(parents=True)
    (out / "images_train").mkdir()
    model = out / "sparse" / "0"
    model.mkdir(parents=True)
    f0 = frames[0][3]
    (model / "cameras.txt").write_text(
        f"1 PINHOLE {f0['w']} {f0['h']} {f0['fl_x']} {f0['fl_y']} {f0['cx']} {f0['cy']}\n")
    lines, test = [], []
    for i, (stem, img, c2w, _) in enumerate(frames):
        name = f"frame_{stem}.png"
        shutil.copy(img, out / "images" / name)
        if i % test_every == 0:
            test.append(f"frame_{stem}")
        else:
            shutil.copy(img, out / "images_train" / name)
        w2c = np.linalg.inv(c2w)
        q, t = _quat_wxyz(w2c[:3, :3]), w2c[:3, 3]
        lines.append(f"{i + 1} {' '.join(repr(float(v)) for v in q)} {' '.join(repr(float(v)) for v in t)} 1 {name}\n\n")
    (model / "images.txt").write_text("".join(lines))
    _write_points3d(model / "points3D.txt", scene)
    test = sorted(test)
    for prompt, obj in prompts.items():
        d = out / "masks" / prompt
        d.mkdir(parents=True)
        for stem, *_ in frames:
            shutil.copy(scene / "masks" / obj / f"{stem}.png", d / f"frame_{stem}.png")
        for idx, view in enumerate(test):
            g = out / "test_mask" / str(idx)
            g.mkdir(parents=True, exist_ok=True)
            shutil.copy(scene / "masks" / obj / f"{view[len('frame_'):]}.png", g / f"{prompt}.png")
    return out, test


def nvos_published(out: Path, layout: str, num_views: int = 12, factor: int = 4,
                   workers: int = 1) -> tuple[Path, Path, Path]:
    """All 8 NVOS tasks in a published layout, for running ``workflows/nvos.toml`` as is:
    ``out/scenes/<scene>/`` (fern, flower, fortress, horns, leaves, orchids, trex; one
    synthetic scene each, other seeds, views renamed to the scene's published names so the
    target and reference views are the published ones), ``out/labels/`` (the 8 tasks) and
    ``out/released/<task>/<view>.JPG`` (the task's object mask of every view at the full
    size, as COB-GS releases its masks). The horns tasks segment two objects of one scene
    (ball, can); the others the ball. Returns (scenes, labels, released)."""
    from cobgs.data.nvos import NVOS_TASKS
    from cobgs.data.synth.scene import generate_scene

    scenes, labels, released = out / "scenes", out / "labels", out / "released"
    by_scene: dict[str, list[str]] = {}
    for task, (scene_name, _, _) in NVOS_TASKS.items():
        by_scene.setdefault(scene_name, []).append(task)
    for seed, (scene_name, tasks) in enumerate(by_scene.items()):
        synth = generate_scene(out / "synthetic" / scene_name, "demo", seed=seed,
                               num_views=num_views, workers=workers, progress=False)
        _, target, reference = NVOS_TASKS[tasks[0]]
        pub = published_names(target, reference, num_views)
        stems = sorted(p.stem for p in (synth / "images").iterdir())
        names = dict(zip(stems, pub))
        objs = dict(zip(tasks, ("ball", "can")))
        write_llff(synth, scenes / scene_name, layout,
                   {objs[t]: released / t for t in tasks}, names=names, factor=factor)
        for t in tasks:
            write_nvos_labels(synth, labels, t, objs[t], stems[pub.index(target)],
                              stems[pub.index(reference)], names=names, factor=factor)
    return scenes, labels, released


def lerf_mask_published(out: Path, num_views: int = 12, workers: int = 1) -> Path:
    """The three LERF-mask scenes with every published prompt, for running
    ``workflows/lerf_mask.toml`` as is: ``out/<scene>/`` as :func:`to_lerf_mask` writes it,
    one synthetic scene each (other seeds); the prompts take the synthetic objects in turn
    (ball, can, crate, ball, ...), so several prompts share an object's masks."""
    from cobgs.data.lerf_mask import LERF_PROMPTS
    from cobgs.data.synth.scene import generate_scene

    objects = ("ball", "can", "crate")
    for seed, (scene_name, prompts) in enumerate(LERF_PROMPTS.items(), start=10):
        synth = generate_scene(out / "synthetic" / scene_name, "demo", seed=seed,
                               num_views=num_views, workers=workers, progress=False)
        to_lerf_mask(synth, out / scene_name,
                     {p: objects[i % len(objects)] for i, p in enumerate(prompts)})
    return out


def write_3dgs_output(train_artifact: Path, scene, out: Path, iteration: int,
                      source_path: Path | str = "/data/scene") -> Path:
    """Write a train stage artifact (``scene.ply`` + ``adam_moments.pt``) as the original
    3DGS code's output folder: ``point_cloud/iteration_<N>/point_cloud.ply``,
    ``cameras.json`` (one entry per training view: position, camera-to-world rotation,
    focal lengths), ``cfg_args`` and ``chkpnt<N>.pth`` (``capture()``'s tuple, the Adam
    state keyed by parameter group in the order the original code creates them)."""
    import torch

    from cobgs.train.adam_moments import read_moments
    from cobgs.gaussians.ply import load_ply

    d = out / "point_cloud" / f"iteration_{iteration}"
    d.mkdir(parents=True)
    shutil.copy(train_artifact / "scene.ply", d / "point_cloud.ply")
    model = load_ply(train_artifact / "scene.ply")
    (out / "cfg_args").write_text(
        f"Namespace(data_device='cuda', eval=False, images='images', model_path='{out}', "
        f"resolution=-1, sh_degree={model.sh_degree}, source_path='{source_path}', "
        f"white_background=False)")
    (out / "cameras.json").write_text(json.dumps([
        {"id": i, "img_name": v.name, "width": v.camera.width, "height": v.camera.height,
         "position": v.camera.center.tolist(), "rotation": v.camera.c2w[:3, :3].tolist(),
         "fy": float(v.camera.fy), "fx": float(v.camera.fx)} for i, v in enumerate(scene.train)]))
    ours = read_moments(train_artifact / "adam_moments.pt")
    order = [("xyz", "means"), ("f_dc", "sh0"), ("f_rest", "shN"), ("opacity", "opacity_logits"),
             ("scaling", "log_scales"), ("rotation", "quats")]
    state = {}
    for k, (_, name) in enumerate(order):
        m = ours[name]
        shape = (-1, 1) if name == "opacity_logits" else m["exp_avg"].shape
        state[k] = {"step": m["step"], "exp_avg": m["exp_avg"].reshape(shape),
                    "exp_avg_sq": m["exp_avg_sq"].reshape(shape)}
    groups = [{"params": [k], "lr": 0.01, "name": g} for k, (g, _) in enumerate(order)]
    n = len(model)
    capture = (model.sh_degree, model.means.detach(), model.data["sh0"].detach(),
               model.data["shN"].detach(), model.data["log_scales"].detach(),
               model.data["quats"].detach(), model.data["opacity_logits"].detach()[:, None],
               torch.zeros(n), torch.zeros(n, 1), torch.zeros(n, 1),
               {"state": state, "param_groups": groups}, 1.0)
    torch.save((capture, iteration), out / f"chkpnt{iteration}.pth")
    return out


def run_stages(folder: Path, text: str, stages=("dataset", "sfm", "masks"), name: str = "w.toml") -> dict:
    """Write the workflow ``text`` to ``folder/name``, run ``stages`` on ``folder/cache`` and
    assert it succeeded; returns {(stage, item id): cache record}."""
    import io

    from pipeline import RunOptions, entries, load_workflow, run_workflow
    from stages.registry import load_registry

    path = folder / name
    path.write_text(text)
    wf = load_workflow(path, load_registry())
    out = io.StringIO()
    summary = run_workflow(wf, RunOptions(cache_dir=folder / "cache", only=tuple(stages)), stream=out)
    assert summary.exit_code == 0, out.getvalue()
    return {(r.stage, r.item.id): r for r in entries(wf, folder / "cache")}



# -- SPIn-NeRF ---------------------------------------------------------------------------------
#: The view names the fixture gives the scenes it writes RGB for (nerf_llff_data's capture
#: names; fern's and orchids' first views are the published IMG_4026 / IMG_4467).
SPIN_FIRST_NAME = {"fern": "IMG_4026", "orchids": "IMG_4467", "leaves": "IMG_2988", "fortress": "IMG_1783",
                   "room": "DJI_20200226_143850_006", "horns": "DJI_20200223_163016_842"}


def spin_view_names(scene: str, n: int) -> list[str]:
    """``n`` view names of a scene in its published copy's style, sorted: nerf_llff_data's capture
    names (fern from IMG_4026, orchids from IMG_4467, room and horns DJI_...), tandt_db's
    000001 ... for truck; stand-ins for the others (pinecone's and the lego's frame names were
    not checked against a download)."""
    if scene in SPIN_FIRST_NAME:
        return published_names(SPIN_FIRST_NAME[scene], SPIN_FIRST_NAME[scene], n)
    if scene == "truck":
        return [f"{i:06d}" for i in range(1, n + 1)]
    if scene == "lego":
        return [f"{i:05d}" for i in range(n)]
    return [f"{scene.upper()}_{i:04d}" for i in range(n)]


def spin_mask_names(scene: str, views: list[str]) -> list[tuple[str, str]]:
    """(annotation name, view) pairs of a scene as the release names them, for the sorted
    ``views``: imageNNN for the indexed LLFF exports (orchids without image014), the view's own
    name for the others, with alternating ``0_`` / ``1_`` split prefixes for the real lego and
    on every third Truck mask."""
    from cobgs.data.spin import SPIN_SCENES

    _, count, rule = SPIN_SCENES[scene]
    if rule == "index":
        idx = [i for i in range(len(views)) if not (scene == "orchids" and i == 14)][:count]
        return [(f"image{i:03d}", views[i]) for i in idx]
    step = max(1, len(views) // count)
    chosen = views[::step][:count]
    if rule == "prefix":
        return [((f"{i % 2}_{v}" if scene == "lego" or i % 3 == 0 else v), v) for i, v in enumerate(chosen)]
    return [(v, v) for v in chosen]


def spin_published(out: Path, rgb: dict, workers: int = 1, seed: int | None = None) -> tuple[Path, dict]:
    """SPIn-NeRF's annotation release in its published layout, ``out/Multiview-Segmentation-Data/``:
    the ten scene folders with the published names and mask counts, each mask with its
    ``_pseudo`` and ``_cutout`` companions, ``annotations.json`` per scene, a README beside
    them and macOS's ``__MACOSX/`` AppleDouble tree.

    ``rgb`` maps the scenes to write RGB for to a synthetic preset's view count; each becomes
    ``out/rgb/<scene>/`` in nerf_llff_data's layout (:func:`write_llff`, factor 4: the masks
    are at images_4's size, as SA3D reads them) and its masks are the synthetic ball's. The
    other scenes' masks are discs over stand-in view names. ``seed``: one generator seed for every
    scene (default: a seed per scene). Returns (release, {scene: RGB folder}).
    """
    from cobgs.data.spin import SPIN_SCENES
    from cobgs.data.synth.scene import generate_scene

    release, folders = out / "Multiview-Segmentation-Data", {}
    release.mkdir(parents=True)
    (release / "README_MVSeg.txt").write_text("Multiview segmentation annotations (fixture).\n")
    for k, (scene, (folder_name, count, rule)) in enumerate(SPIN_SCENES.items()):
        folder = release / folder_name
        folder.mkdir()
        if scene in rgb:
            synth = generate_scene(out / "synthetic" / scene, "demo", seed=k if seed is None else seed,
                                   num_views=rgb[scene],
                                   workers=workers, progress=False)
            stems = sorted(p.stem for p in (synth / "images").iterdir())
            pub = spin_view_names(scene, len(stems))
            names = dict(zip(stems, pub))
            folders[scene] = write_llff(synth, out / "rgb" / scene, "nerf_llff_data", {}, names=names, factor=4)
            back = {v: k for k, v in names.items()}
            masks = {v: cv2.imread(str(synth / "masks" / "ball" / f"{back[v]}.png"), cv2.IMREAD_GRAYSCALE)
                     for v in pub}
            views = pub
        else:
            views = spin_view_names(scene, 2 * count + 1 if scene == "truck" else count + 2)
            disc = np.zeros((30, 40), np.uint8)
            cv2.circle(disc, (20, 15), 8, 255, -1)
            masks = {v: disc for v in views}
            if scene != "fork":  # (fork's RGB is not public)
                folders[scene] = out / "rgb" / scene
                (folders[scene] / "images").mkdir(parents=True)
                for v in views:  # stand-in photos (kind spin reads a folder of photos without poses too)
                    cv2.imwrite(str(folders[scene] / "images" / f"{v}.png"), cv2.merge([disc, disc // 2, disc]))
        entries = []
        for ann, v in spin_mask_names(scene, sorted(views)):
            m = masks[v]
            cv2.imwrite(str(folder / f"{ann}.png"), m)
            cv2.imwrite(str(folder / f"{ann}_pseudo.png"), cv2.merge([m // 2, m, m // 2]))
            cv2.imwrite(str(folder / f"{ann}_cutout.png"), cv2.merge([m, m, m, m]))
            entries.append({"file": f"{ann}.png"})
        (folder / "annotations.json").write_text(json.dumps(entries))
        mac = out / "__MACOSX" / "Multiview-Segmentation-Data" / folder_name  # beside it, as macOS zips
        mac.mkdir(parents=True)
        (mac / f"._{entries[0]['file']}").write_bytes(b"\x00\x05\x16\x07")
    return release, folders
