"""Synthetic scene generator: determinism, file layout, masks against projected geometry."""

from __future__ import annotations

import dataclasses
import filecmp
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from cobgs.errors import InputError
from cobgs.data.synth import scene as synthetic
from cobgs.data.synth.primitives import Box, Cylinder, Plane, Sphere, rotation_from_euler_deg

# Small enough to render in ~1 s, large enough that every object spans many pixels.
SMALL = dict(width_px=120, height_px=90, num_views=9, supersampling=2)


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth") / "demo"
    synthetic.generate_scene(out, "demo", seed=3, progress=False, **SMALL)
    return out


def _read(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert img is not None, path
    return img


def _w2c_opencv(transform_matrix) -> np.ndarray:
    """world->camera in OpenCV axes from a transforms.json camera->world (OpenGL axes),
    written independently of the generator's helpers."""
    c2w = np.asarray(transform_matrix, dtype=np.float64)
    c2w_cv = c2w.copy()
    c2w_cv[:3, 1] *= -1.0  # OpenGL +y up -> OpenCV +y down
    c2w_cv[:3, 2] *= -1.0  # OpenGL looks down -z -> OpenCV looks down +z
    return np.linalg.inv(c2w_cv)


def _project(frame: dict, pts: np.ndarray):
    w2c = _w2c_opencv(frame["transform_matrix"])
    pc = pts @ w2c[:3, :3].T + w2c[:3, 3]
    u = frame["fl_x"] * pc[:, 0] / pc[:, 2] + frame["cx"]
    v = frame["fl_y"] * pc[:, 1] / pc[:, 2] + frame["cy"]
    return u, v, pc[:, 2], np.linalg.inv(w2c)[:3, 3]


def _surface_samples(obj: dict, n: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """Points [n, 3] on an object's surface with outward normals [n, 3], from scene.json."""
    p = obj["params"]
    if obj["kind"] == "sphere":
        d = rng.standard_normal((n, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return np.asarray(p["center"]) + p["radius"] * d, d
    if obj["kind"] == "box":
        h = np.asarray(p["half_extents"])
        r = np.asarray(p["rotation"])
        q = rng.uniform(-1, 1, (n, 3)) * h
        face = rng.integers(0, 3, n)
        sign = rng.choice([-1.0, 1.0], n)
        q[np.arange(n), face] = sign * h[face]
        nl = np.zeros((n, 3))
        nl[np.arange(n), face] = sign
        return np.asarray(p["center"]) + q @ r.T, nl @ r.T
    if obj["kind"] == "cylinder":
        a = np.asarray(p["axis"]) / np.linalg.norm(p["axis"])
        x = np.cross([1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0], a)
        x /= np.linalg.norm(x)
        y = np.cross(a, x)
        ang = rng.uniform(0, 2 * math.pi, n)
        z = rng.uniform(0, p["height"], n)
        radial = np.cos(ang)[:, None] * x + np.sin(ang)[:, None] * y
        pts = np.asarray(p["base"]) + p["radius"] * radial + z[:, None] * a
        nrm = radial.copy()
        cap = rng.random(n) < 0.3
        rr = p["radius"] * np.sqrt(rng.random(n))
        top = rng.random(n) < 0.5
        capz = np.where(top, p["height"], 0.0)
        pts[cap] = (np.asarray(p["base"]) + rr[cap, None] * radial[cap] + capz[cap, None] * a)
        nrm[cap] = np.where(top[cap, None], a, -a)
        return pts, nrm
    raise AssertionError(f"unknown kind {obj['kind']}")


def test_layout_and_metadata(scene_dir):
    tf = json.loads((scene_dir / "transforms.json").read_text())
    meta = json.loads((scene_dir / "scene.json").read_text())
    assert meta["generator"] == "cobgs.data.synth.scene" and meta["version"] == 1
    assert meta["preset"] == "demo" and meta["seed"] == 3 and meta["trajectory"] == "forward"
    assert meta["image_size"] == [120, 90] and meta["supersampling"] == 2
    names = [o["name"] for o in meta["objects"]]
    assert [o["id"] for o in meta["objects"]] == list(range(1, len(names) + 1))
    assert len(names) == 3 and all(o["target"] for o in meta["objects"])
    assert sorted(p.name for p in (scene_dir / "masks").iterdir()) == sorted(names)
    assert sorted(p.name for p in (scene_dir / "coverage").iterdir()) == sorted(names)
    assert len(tf["frames"]) == 9
    # Every 8th view (file order) is held out.
    assert tf["test_filenames"] == ["images/0000.png", "images/0008.png"]
    for i, fr in enumerate(tf["frames"]):
        assert fr["file_path"] == f"images/{i:04d}.png"
        assert (fr["w"], fr["h"]) == (120, 90)
        assert fr["cx"] == 60.0 and fr["cy"] == 45.0 and fr["fl_x"] == fr["fl_y"] > 0
        m = np.asarray(fr["transform_matrix"])
        assert m.shape == (4, 4) and np.allclose(m[3], [0, 0, 0, 1])
        assert np.allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-9)
        assert np.linalg.det(m[:3, :3]) == pytest.approx(1.0)
        img = _read(scene_dir / fr["file_path"])
        assert img.shape == (90, 120, 3) and img.dtype == np.uint8
        assert img.std() > 20  # textured, not blank
        for n in names:
            assert (scene_dir / "masks" / n / f"{i:04d}.png").is_file()


def test_masks_follow_majority_of_subsamples(scene_dir):
    """mask == (2 * hits > S) with hits recovered from the coverage map; coverages of all
    objects sum to at most one pixel (first hit only)."""
    meta = json.loads((scene_dir / "scene.json").read_text())
    s = meta["subsamples_per_pixel"]
    assert s == 4
    for i in range(9):
        total = np.zeros((90, 120), dtype=np.int64)
        for o in meta["objects"]:
            m = _read(scene_dir / "masks" / o["name"] / f"{i:04d}.png")
            cov = _read(scene_dir / "coverage" / o["name"] / f"{i:04d}.png")
            assert m.ndim == 2 and set(np.unique(m)) <= {0, 255}
            hits = np.rint(cov.astype(np.float64) * s / 255.0).astype(np.int64)
            assert np.array_equal(np.rint(255.0 * hits / s).astype(np.uint8), cov)
            assert np.array_equal(m == 255, 2 * hits > s)
            total += hits
        assert total.max() <= s


def test_amodal_masks_hold_the_visible_ones(scene_dir):
    """amodal/<object>/ holds the held-out views only: the whole silhouette (occluders
    ignored) contains the visible mask, and is larger where something hides the object."""
    from cobgs.data.synth.render import SynthScene, render_view
    from cobgs.data.synth.scene import build_scene
    import dataclasses as dc

    meta = json.loads((scene_dir / "scene.json").read_text())
    names = [o["name"] for o in meta["objects"]]
    assert sorted(p.name for p in (scene_dir / "amodal").iterdir()) == sorted(names)
    hidden = 0
    for n in names:
        assert sorted(p.name for p in (scene_dir / "amodal" / n).iterdir()) == ["0000.png", "0008.png"]
        for stem in ("0000", "0008"):
            am = _read(scene_dir / "amodal" / n / f"{stem}.png") == 255
            vis = _read(scene_dir / "masks" / n / f"{stem}.png") == 255
            assert not (vis & ~am).any()
            hidden += int((am & ~vis).sum())
    assert hidden > 0  # the demo scene has objects partly hidden behind others
    # One object alone, ray-cast as an ordinary scene: its first-hit mask is the silhouette.
    p, synth, cams = build_scene("demo", 3, width_px=120, height_px=90, supersampling=2, num_views=9)
    alone = SynthScene(objects=(dc.replace(synth.objects[0], id=1),), background=(), light_dir=synth.light_dir,
                       ambient=synth.ambient, sky=synth.sky)
    rv = render_view(alone, cams[8], 2)
    expect = 2 * rv.hits[0].astype(np.int64) > rv.subsamples
    assert np.array_equal(_read(scene_dir / "amodal" / names[0] / "0008.png") == 255, expect)


def test_deterministic_for_a_seed(scene_dir, tmp_path):
    """Bit-identical files for the same seed, also when views render in worker processes."""
    again = synthetic.generate_scene(tmp_path / "again", "demo", seed=3, progress=False,
                                     workers=2, **SMALL)
    cmp = filecmp.dircmp(scene_dir, again)
    files = [p.relative_to(scene_dir) for p in scene_dir.rglob("*") if p.is_file()]
    assert len(files) == 2 + 9 * (1 + 2 * 3) + 2 * 3  # + amodal masks of the 2 held-out views
    for rel in files:
        assert (scene_dir / rel).read_bytes() == (again / rel).read_bytes(), rel
    assert not cmp.left_only and not cmp.right_only
    other = synthetic.generate_scene(tmp_path / "other", "demo", seed=4, progress=False, **SMALL)
    assert (other / "images/0000.png").read_bytes() != (scene_dir / "images/0000.png").read_bytes()


def test_masks_match_projected_geometry(scene_dir):
    """Project dense front-facing surface samples of each object (from scene.json) with the
    saved cameras: the mask never leaves the projected silhouette, and the silhouette's
    interior is the object's mask unless another object covers it."""
    tf = json.loads((scene_dir / "transforms.json").read_text())
    meta = json.loads((scene_dir / "scene.json").read_text())
    rng = np.random.default_rng(0)
    k3 = np.ones((3, 3), np.uint8)
    for i, fr in enumerate(tf["frames"]):
        masks = {o["name"]: _read(scene_dir / "masks" / o["name"] / f"{i:04d}.png") > 0
                 for o in meta["objects"]}
        for o in meta["objects"]:
            pts, nrm = _surface_samples(o, 60_000, rng)  # >10 per covered pixel
            u, v, z, eye = _project(fr, pts)
            front = np.einsum("ij,ij->i", nrm, eye - pts) > 0
            inside = front & (z > 0) & (u >= 0) & (u < 120) & (v >= 0) & (v < 90)
            sil = np.zeros((90, 120), np.uint8)
            sil[np.floor(v[inside]).astype(int), np.floor(u[inside]).astype(int)] = 1
            mask = masks[o["name"]]
            others = np.zeros_like(mask)
            for n, m in masks.items():
                if n != o["name"]:
                    others |= m
            # No mask pixel outside the (1-px grown) silhouette.
            assert not np.any(mask & ~cv2.dilate(sil, k3).astype(bool)), (i, o["name"])
            # The silhouette's interior is the object or an occluder.
            core = cv2.erode(sil, k3).astype(bool)
            hole = core & ~mask & ~cv2.dilate(others.astype(np.uint8), k3).astype(bool)
            assert not np.any(hole), (i, o["name"], int(hole.sum()))
            assert mask.sum() > 20, (i, o["name"])


def test_visible_point_lands_on_its_mask(scene_dir):
    """The point of the ball nearest to each camera projects onto the ball's mask (or onto
    an occluder's) and does so, unoccluded, in several views."""
    tf = json.loads((scene_dir / "transforms.json").read_text())
    meta = json.loads((scene_dir / "scene.json").read_text())
    ball = next(o for o in meta["objects"] if o["kind"] == "sphere")
    c, r = np.asarray(ball["params"]["center"]), ball["params"]["radius"]
    on_mask = 0
    for i, fr in enumerate(tf["frames"]):
        eye = np.linalg.inv(_w2c_opencv(fr["transform_matrix"]))[:3, 3]
        p = c + r * (eye - c) / np.linalg.norm(eye - c)
        u, v, z, _ = _project(fr, p[None])
        col, row = int(math.floor(u[0])), int(math.floor(v[0]))
        assert z[0] > 0 and 0 <= col < 120 and 0 <= row < 90
        hit = {o["name"]: _read(scene_dir / "masks" / o["name"] / f"{i:04d}.png")[row, col] > 0
               for o in meta["objects"]}
        assert any(hit.values()), i
        on_mask += hit[ball["name"]]
    assert on_mask >= 5


def test_ball_coverage_matches_analytic_area(scene_dir):
    """Sub-pixel check of the camera convention (pixel centres at +0.5): the ball's
    coverage map agrees with its area fraction computed here on a fine 8x8 grid per pixel
    from the saved camera, and the two centroids agree to a small fraction of a pixel."""
    tf = json.loads((scene_dir / "transforms.json").read_text())
    meta = json.loads((scene_dir / "scene.json").read_text())
    ball = next(o for o in meta["objects"] if o["kind"] == "sphere")
    c, r = np.asarray(ball["params"]["center"]), ball["params"]["radius"]
    g = (np.arange(8) + 0.5) / 8
    cols = (np.arange(120)[:, None] + g[None, :]).ravel()
    rows = (np.arange(90)[:, None] + g[None, :]).ravel()
    uu, vv = np.meshgrid(cols, rows)
    for i, fr in enumerate(tf["frames"]):
        c2w = np.linalg.inv(_w2c_opencv(fr["transform_matrix"]))
        dirs = np.stack([(uu - fr["cx"]) / fr["fl_x"], (vv - fr["cy"]) / fr["fl_y"],
                         np.ones_like(uu)], -1) @ c2w[:3, :3].T
        dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
        oc = c2w[:3, 3] - c
        b = dirs @ oc
        hit = (b * b - (oc @ oc - r * r) >= 0) & (b < 0)
        exact = hit.reshape(90, 8, 120, 8).mean(axis=(1, 3))
        cov = _read(scene_dir / "coverage" / ball["name"] / f"{i:04d}.png") / 255.0
        others = sum(_read(scene_dir / "coverage" / o["name"] / f"{i:04d}.png").astype(int)
                     for o in meta["objects"] if o is not ball)
        free = cv2.dilate((others > 0).astype(np.uint8), np.ones((3, 3), np.uint8)) == 0
        assert np.abs(exact - cov)[free].max() <= 0.5 + 1e-9  # 2x2 samples: steps of 1/4
        assert np.abs(exact - cov)[free].mean() < 0.01
        yy, xx = np.nonzero(free)
        we, wc = exact[free], cov[free]
        assert we.sum() > 30
        for coord in (xx, yy):
            assert abs((coord * we).sum() / we.sum() - (coord * wc).sum() / wc.sum()) < 0.08, i


def test_bench_presets_have_thin_and_touching_objects():
    for name in ("forward", "orbit"):
        _, scene, cams = synthetic.build_scene(name, seed=0)
        objs = scene.objects
        assert len(objs) >= 4
        assert len(cams) == synthetic.PRESETS[name].num_views
        thin = [o for o in objs if isinstance(o.shape, Cylinder) and o.shape.radius < 0.03]
        assert thin, name
        # A ball resting on a box: sphere centre exactly radius above the box top.
        boxes = [o.shape for o in objs if isinstance(o.shape, Box)]
        balls = [o.shape for o in objs if isinstance(o.shape, Sphere)]
        assert any(abs(s.center[2] - (b.center[2] + b.half_extents[2] + s.radius)) < 1e-12
                   for s in balls for b in boxes)
        # Every object but that ball stands on the ground (lowest point at z = 0).
        lows = []
        for o in objs:
            sh = o.shape
            if isinstance(sh, Sphere):
                lows.append(sh.center[2] - sh.radius)
            elif isinstance(sh, Box):
                lows.append(sh.lowest_z())
            else:
                lows.append(sh.base[2])
        assert sum(abs(z) < 1e-9 for z in lows) == len(objs) - 1


def test_primitives_intersections():
    o = np.array([[0.0, -5.0, 0.5], [0.0, -5.0, 3.0]])
    d = np.array([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
    s = Sphere((0.0, 0.0, 0.5), 0.5)
    assert s.intersect(o, d) == pytest.approx([4.5, np.inf])
    b = Box((0.0, 0.0, 0.5), (0.5, 0.5, 0.5), rotation_from_euler_deg(45.0))
    assert b.intersect(o, d)[0] == pytest.approx(5.0 - 0.5 * math.sqrt(2))
    n, _ = b.surface(np.array([[0.25, -0.25, 0.5]]))
    assert n[0] == pytest.approx([math.sqrt(0.5), -math.sqrt(0.5), 0.0])
    assert b.lowest_z() == pytest.approx(0.0)
    c = Cylinder((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 0.25, 1.0)
    down = np.array([[0.1, 0.0, 3.0]]), np.array([[0.0, 0.0, -1.0]])
    assert c.intersect(*down) == pytest.approx([2.0])  # the top cap
    assert c.intersect(o, d) == pytest.approx([4.75, np.inf])
    g = Plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0))
    assert g.intersect(*down) == pytest.approx([3.0])
    assert np.isinf(g.intersect(o, d)).all()  # parallel rays
    with pytest.raises(InputError, match="radius"):
        Sphere((0.0, 0.0, 0.0), -1.0)


def test_bad_arguments(tmp_path):
    with pytest.raises(InputError, match="unknown synthetic preset"):
        synthetic.generate_scene(tmp_path / "x", "nope")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("x")
    with pytest.raises(InputError, match="not empty"):
        synthetic.generate_scene(tmp_path / "full", "demo", **SMALL)
    with pytest.raises(InputError, match="supersampling"):
        synthetic.generate_scene(tmp_path / "y", "demo", supersampling=0)


def test_interrupted_generation_leaves_nothing(tmp_path, monkeypatch):
    calls = {"n": 0}
    real = synthetic._write_png

    def flaky(path, array):
        calls["n"] += 1
        if calls["n"] == 10:
            raise KeyboardInterrupt
        real(path, array)

    monkeypatch.setattr(synthetic, "_write_png", flaky)
    with pytest.raises(KeyboardInterrupt):
        synthetic.generate_scene(tmp_path / "scene", "demo", progress=False, **SMALL)
    assert list(tmp_path.iterdir()) == []


def _cli(argv) -> int:
    """Run a `cobgs` command through this provider only (others may be mid-edit)."""
    import argparse

    from stages.commands import synth as synth_cmd

    parser = argparse.ArgumentParser(prog="cobgs")
    synth_cmd.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(argv)
    return args.func(args)


def test_cli_matches_library(tmp_path):
    from cobgs.configs import MaskNoiseParams
    from stages.commands import synth as synth_cmd

    assert set(synth_cmd.PRESET_NAMES) == set(synthetic.PRESETS)
    noise_fields = {f.name for f in dataclasses.fields(MaskNoiseParams)} - {"seed"}
    assert {n for n, _, _ in synth_cmd.NOISE_OPTIONS} == noise_fields
    out = tmp_path / "s"
    rc = _cli(["synth", "--preset", "demo", "--out", str(out), "--seed", "1", "--size", "48x36",
               "--views", "3", "--supersampling", "1", "-q"])
    assert rc == 0
    assert json.loads((out / "scene.json").read_text())["image_size"] == [48, 36]
    rc = _cli(["synth-noise", str(out), "--out", str(tmp_path / "noisy"), "--drop-rate", "1", "-q"])
    assert rc == 0
    pngs = list((tmp_path / "noisy").rglob("*.png"))
    assert len(pngs) == 3 * 3
    for f in pngs:
        assert not _read(f).any()
    with pytest.raises(InputError, match="not empty"):
        _cli(["synth", "--out", str(out), "-q"])
    with pytest.raises(SystemExit):
        _cli(["synth", "--out", str(out), "--size", "48by36"])


def test_render_workers_end_with_a_killed_parent(tmp_path):
    """A SIGKILLed process that was rendering with worker processes (the dataset stage with
    ``workers = 2``) leaves no worker behind: they end within seconds instead of waiting on
    their task queue forever under PID 1."""
    import os
    import signal
    import subprocess
    import sys
    import time

    code = ("from cobgs.data.synth.scene import generate_scene\n"
            f"generate_scene({str(tmp_path / 'scene')!r}, 'forward', seed=0, num_views=60, "
            "workers=2, progress=False)\n")
    proc = subprocess.Popen([sys.executable, "-c", code], start_new_session=True)
    children: list[int] = []
    deadline = time.monotonic() + 60
    try:
        while len(children) < 2 and time.monotonic() < deadline and proc.poll() is None:
            try:
                children = [int(c) for c in
                            Path(f"/proc/{proc.pid}/task/{proc.pid}/children").read_text().split()]
            except OSError:
                pass
            time.sleep(0.02)
        assert len(children) >= 2, "the render workers never started"
        time.sleep(0.3)  # inside the pool's task loop
        os.kill(proc.pid, signal.SIGKILL)  # the parent only, as the OOM killer does
        proc.wait(timeout=30)
        left = set(children)
        deadline = time.monotonic() + 5
        while left and time.monotonic() < deadline:
            for pid in list(left):
                try:
                    state = Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0]
                except OSError:
                    state = "gone"
                if state in ("gone", "Z"):
                    left.discard(pid)
            time.sleep(0.05)
        assert not left, f"render workers {sorted(left)} outlived their parent"
    finally:
        for pid in children:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
