"""Scene readers on the shared real data (fern, lego) and on fixtures written here."""

import json
import math
import re

import cv2
import numpy as np
import pytest
import torch

from cobgs.render.camera import Camera
from cobgs.data.colmap import read_colmap
from cobgs.data.llff import read_llff
from cobgs.data.readers import detect_format, read_scene
from cobgs.data.scene import load_rgb
from cobgs.data.transforms import read_transforms
from cobgs.errors import DataError


# -- helpers ----------------------------------------------------------------------------------
def _fundamental(c1: Camera, c2: Camera) -> np.ndarray:
    T = (c2.viewmat.double() @ torch.linalg.inv(c1.viewmat.double())).numpy()
    R, t = T[:3, :3], T[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    K1, K2 = c1.K.double().numpy(), c2.K.double().numpy()
    return np.linalg.inv(K2).T @ (tx @ R) @ np.linalg.inv(K1)


def _median_epipolar_px(v1, v2, F) -> float:
    sift = cv2.SIFT_create()
    grey = lambda v: cv2.cvtColor((v.image.numpy() * 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)
    k1, d1 = sift.detectAndCompute(grey(v1), None)
    k2, d2 = sift.detectAndCompute(grey(v2), None)
    matches = [a for a, b in cv2.BFMatcher().knnMatch(d1, d2, k=2) if a.distance < 0.7 * b.distance]
    assert len(matches) > 30
    # OpenCV keypoints have pixel centres at integers; our K puts them at +0.5.
    p1 = np.array([k1[m.queryIdx].pt for m in matches]) + 0.5
    p2 = np.array([k2[m.trainIdx].pt for m in matches]) + 0.5
    h1, h2 = np.c_[p1, np.ones(len(p1))], np.c_[p2, np.ones(len(p2))]
    lines = h1 @ F.T
    return float(np.median(np.abs((h2 * lines).sum(1)) / np.linalg.norm(lines[:, :2], axis=1)))


def _write_png(path, arr):
    path.parent.mkdir(parents=True, exist_ok=True)
    arr = np.asarray(arr)
    if arr.ndim == 3 and arr.shape[2] == 3:
        arr = arr[:, :, ::-1]
    cv2.imwrite(str(path), arr)


# -- shared data ----------------------------------------------------------------------------
def test_fern_llff_poses_are_consistent_with_images(shared_data):
    scene = read_llff(shared_data / "llff_fern", downscale=8)
    assert len(scene.train) == 17 and len(scene.test) == 3
    assert [v.name for v in scene.test] == ["IMG_4026", "IMG_4034", "IMG_4042"]
    v0 = scene.train[0]
    assert v0.image.shape == (378, 504, 3) and v0.image.dtype == torch.float32
    assert v0.camera.fx == pytest.approx(3260.5 * 504 / 4032, rel=1e-3)
    assert scene.points is None and scene.kind == "llff"
    # The poses must explain the images: SIFT matches lie on the epipolar lines.
    views = scene.train
    for i, j in [(0, 1), (2, 9)]:
        err = _median_epipolar_px(views[i], views[j], _fundamental(views[i].camera, views[j].camera))
        assert err < 1.0, (i, j, err)
    # Negative control: reading LLFF's (down, right, back) columns as OpenCV axes is wrong.
    raw = np.load(shared_data / "llff_fern" / "poses_bounds.npy")[:, :15].reshape(-1, 3, 5)
    names = sorted(v.name for v in scene.views)
    bad = []
    for v in (views[0], views[1]):
        k = names.index(v.name)
        c2w = np.eye(4)
        c2w[:3, :4] = raw[k][:, :4]
        bad.append(Camera.from_c2w(c2w, v.camera.fx, v.camera.fy, v.camera.cx, v.camera.cy, 504, 378))
    assert _median_epipolar_px(views[0], views[1], _fundamental(bad[0], bad[1])) > 3.0


def test_fern_explicit_holdout_and_images_4(shared_data):
    scene = read_llff(shared_data / "llff_fern", downscale=4, test_names=["IMG_4027"])
    assert [v.name for v in scene.test] == ["IMG_4027"] and len(scene.train) == 19
    assert scene.train[0].image.shape == (756, 1008, 3)
    with pytest.raises(DataError, match="IMG_9999"):
        read_llff(shared_data / "llff_fern", downscale=8, test_names=["IMG_9999"])
    assert detect_format(shared_data / "llff_fern") == "llff"


def test_lego_blender_alpha_masks(shared_data):
    scene = read_scene(shared_data / "nerf_synthetic_lego", downscale=4)
    assert scene.kind == "blender" and len(scene.train) == 80 and len(scene.test) == 20
    assert scene.train[0].name == "r_0" and scene.test[0].name == "r_80"
    v = scene.train[0]
    assert v.image.shape == (200, 200, 3) and (v.camera.width, v.camera.height) == (200, 200)
    assert v.camera.fx == pytest.approx(0.5 * 200 / math.tan(0.5 * 0.6911112070083618), rel=1e-6)
    assert scene.background == (1.0, 1.0, 1.0)
    m = v.masks["object"]
    assert m.dtype == torch.bool and 0.05 < m.float().mean() < 0.6
    assert torch.equal(m, v.coverage["object"] > 0.5)
    # Background pixels are composited on white; the object sits at the world origin.
    assert torch.allclose(v.image[~m].mean(0), torch.ones(3), atol=0.02)
    for view in scene.train[:10] + scene.test[:5]:
        uv, z = view.camera.project(torch.zeros(1, 3))
        assert z.item() > 0 and torch.allclose(uv, torch.tensor([[100.0, 100.0]]), atol=2.0)
        # The object mask is roughly centred too (the origin projects into the lego).
        assert view.masks["object"][95:105, 95:105].float().mean() > 0.3
    assert scene.init_bounds == ([-1.3] * 3, [1.3] * 3)
    # Compositing is C_premultiplied + bg (1 - alpha), computed after area resizing.
    black, alpha = load_rgb(v.path, (200, 200), background=(0.0, 0.0, 0.0))
    assert torch.allclose(alpha, v.coverage["object"])
    assert torch.allclose(v.image - black, (1 - alpha)[:, :, None].expand(-1, -1, 3), atol=1e-5)


# -- COLMAP fixture ---------------------------------------------------------------------------
def _colmap_fixture(root, binary=False):
    """Two cameras (PINHOLE, OPENCV with distortion), images with a blob where a 3D point lands."""
    import pycolmap

    W, H = 80, 60
    point = np.array([0.8, -0.5, 0.1])  # far off-centre, where distortion is strong
    cams = {
        1: ("PINHOLE", [70.0, 72.0, 40.0, 30.0]),
        2: ("OPENCV", [75.0, 75.0, 41.0, 29.0, -0.25, 0.05, 0.001, -0.002]),
    }
    # (qw, qx, qy, qz, tx, ty, tz, camera, name)
    poses = [
        (1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 3.0, 1, "a.png"),
        (0.9659258, 0.0, 0.258819, 0.0, -0.5, 0.2, 3.2, 2, "b.png"),
        (0.9848078, 0.1736482, 0.0, 0.0, 0.4, 0.0, 2.5, 2, "c.png"),
    ]
    sparse = root / "sparse" / "0"
    sparse.mkdir(parents=True)
    (sparse / "cameras.txt").write_text("".join(f"{i} {m} {W} {H} {' '.join(map(str, p))}\n" for i, (m, p) in cams.items()))
    lines = []
    for k, (qw, qx, qy, qz, tx, ty, tz, cid, name) in enumerate(poses, 1):
        lines.append(f"{k} {qw} {qx} {qy} {qz} {tx} {ty} {tz} {cid} {name}\n\n")
        R = _quat_rot(qw, qx, qy, qz)
        pc = R @ point + np.array([tx, ty, tz])
        cam = pycolmap.Camera.create_from_model_name(cid, cams[cid][0], 1.0, W, H)
        cam.params = cams[cid][1]
        u, v = cam.img_from_cam(pc[None])[0]
        yy, xx = np.mgrid[0:H, 0:W] + 0.5
        blob = np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * 1.2**2))
        img = np.stack([blob, 0.5 * blob, np.full_like(blob, 0.2)], 2)
        _write_png(root / "images" / name, np.round(img * 255).astype(np.uint8))
    (sparse / "images.txt").write_text("".join(lines))
    (sparse / "points3D.txt").write_text("1 0.8 -0.5 0.1 200 100 50 0.5\n2 1 1 1 10 20 30 0.5\n")
    if binary:
        rec = pycolmap.Reconstruction(sparse)
        for f in sparse.iterdir():
            f.unlink()
        rec.write_binary(str(sparse))
    return point


def _quat_rot(w, x, y, z):
    n = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def _blob_centre(img: torch.Tensor) -> np.ndarray:
    w = img[:, :, 0].double().numpy()
    w = np.where(w > 0.3 * w.max(), w, 0)
    yy, xx = np.mgrid[0 : w.shape[0], 0 : w.shape[1]] + 0.5
    return np.array([(w * xx).sum() / w.sum(), (w * yy).sum() / w.sum()])


@pytest.mark.parametrize("binary", [False, True])
def test_colmap_model_with_undistortion(tmp_path, binary):
    point = _colmap_fixture(tmp_path, binary)
    assert detect_format(tmp_path) == "colmap"
    scene = read_colmap(tmp_path, test_every=0)
    assert [v.name for v in scene.train] == ["a", "b", "c"]
    assert torch.allclose(scene.points, torch.tensor([[0.8, -0.5, 0.1], [1.0, 1.0, 1.0]]))
    assert torch.allclose(scene.points_rgb[0], torch.tensor([200, 100, 50]) / 255.0)
    a = scene.train[0]
    assert torch.allclose(a.camera.viewmat[:3, 3], torch.tensor([0.0, 0.0, 3.0]))
    assert a.camera.fx == pytest.approx(70.0) and a.camera.fy == pytest.approx(72.0)
    for v in scene.train:  # PINHOLE as is; OPENCV undistorted: the blob lands where we project
        uv, _ = v.camera.project(torch.from_numpy(point[None]).float())
        assert np.allclose(_blob_centre(v.image), uv[0].numpy(), atol=0.3), v.name
    assert scene.train[1].camera.width != 80 or scene.train[1].camera.fx != 75.0  # really undistorted


def test_colmap_errors(tmp_path):
    _colmap_fixture(tmp_path)
    (tmp_path / "images" / "b.png").unlink()
    with pytest.raises(DataError, match="b.png"):
        read_colmap(tmp_path)
    bad = tmp_path / "bad"
    (bad / "sparse" / "0").mkdir(parents=True)
    (bad / "sparse" / "0" / "cameras.txt").write_text("1 NOT_A_MODEL 80 60 1 2 3\n")
    (bad / "sparse" / "0" / "images.txt").write_text("")
    (bad / "sparse" / "0" / "points3D.txt").write_text("")
    with pytest.raises(DataError, match="COLMAP model"):
        read_colmap(bad)
    with pytest.raises(DataError, match="no COLMAP model"):
        read_colmap(tmp_path / "images")


# -- transforms.json fixture --------------------------------------------------------------------
def _transforms_fixture(root, n=5, W=32, H=24):
    frames = []
    for i in range(n):
        img = np.zeros((H, W, 3), np.uint8)
        img[:, :, 0] = 10 * i
        img[4:12, 8:20] = 255
        _write_png(root / "images" / f"{i:04d}.png", img)
        mask = np.zeros((H, W), np.uint8)
        mask[4:12, 8:20] = 255
        if i != 2:  # frame 2 has no annotation for "box"
            _write_png(root / "masks" / "box" / f"{i:04d}.png", mask)
        c2w = np.eye(4)
        c2w[:3, 3] = [0.5 * i, 0.0, 4.0]
        frames.append({
            "file_path": f"images/{i:04d}.png",
            "transform_matrix": c2w.tolist(),
            "fl_x": 30.0 + i, "fl_y": 31.0 + i, "cx": 16.0, "cy": 12.0, "w": W, "h": H,
        })
    meta = {"camera_model": "PINHOLE", "fl_x": 1.0, "fl_y": 1.0, "cx": 0, "cy": 0, "w": W, "h": H,
            "frames": frames, "test_filenames": ["images/0003.png"]}
    (root / "transforms.json").write_text(json.dumps(meta))
    return meta


def test_transforms_with_masks(tmp_path):
    _transforms_fixture(tmp_path)
    scene = read_scene(tmp_path, downscale=2)
    assert scene.kind == "transforms" and scene.object_names == ["box"]
    assert [v.name for v in scene.test] == ["0003"]
    assert [v.name for v in scene.train] == ["0000", "0001", "0002", "0004"]
    v = scene.train[1]
    assert v.image.shape == (12, 16, 3)
    assert v.camera.fx == pytest.approx(31.0 / 2) and v.camera.fy == pytest.approx(32.0 / 2)  # per-frame wins
    assert v.camera.cx == pytest.approx(8.0)
    m = v.masks["box"]
    assert m.shape == (12, 16) and m.sum() == 4 * 6 and m[2:6, 4:10].all()
    assert "box" not in scene.train[2].masks  # missing file = no annotation
    # OpenGL pose: camera at z = 4 looking down -z sees the origin in front of it.
    uv, z = scene.train[0].camera.project(torch.zeros(1, 3))
    assert z.item() == pytest.approx(4.0) and torch.allclose(uv, torch.tensor([[8.0, 6.0]]))
    # Explicit held-out names override the file's list.
    s2 = read_transforms(tmp_path, test_names=["0000", "0001.png"])
    assert [v.name for v in s2.test] == ["0000", "0001"]


def test_transforms_errors(tmp_path):
    meta = _transforms_fixture(tmp_path)
    _write_png(tmp_path / "masks" / "box" / "0001.png", np.zeros((10, 10), np.uint8))
    with pytest.raises(DataError, match=r"0001\.png.*mask is 10x10"):
        read_transforms(tmp_path)
    _write_png(tmp_path / "masks" / "box" / "0001.png", np.zeros((24, 32), np.uint8))
    meta["frames"][0]["camera_model"] = "FISHEYE"
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DataError, match="FISHEYE"):
        read_transforms(tmp_path)
    meta["frames"][0].pop("camera_model")
    meta["frames"][4]["file_path"] = "images/missing.png"
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DataError, match="missing.png"):
        read_transforms(tmp_path)
    (tmp_path / "transforms.json").write_text("{not json")
    with pytest.raises(DataError, match="transforms.json"):
        read_transforms(tmp_path)
    (tmp_path / "images" / "0000.png").write_bytes(b"garbage")
    with pytest.raises(DataError, match="unreadable image"):
        from cobgs.data.scene import read_image_array

        read_image_array(tmp_path / "images" / "0000.png")


def _pose_with(i, value):
    c2w = np.eye(4)
    c2w[:3, 3] = [0.5 * i, 0.0, 4.0]
    if value == "nan":
        c2w[0, 3] = float("nan")
    elif value == "singular":
        c2w[:3, :3] = 0.0
    elif value == "scaled":
        c2w[:3, :3] *= 2.0
    elif value == "mirrored":
        c2w[0, 0] = -1.0
    elif value == "last_row":
        c2w[3, 2] = 1.0
    return c2w.tolist()


@pytest.mark.parametrize("change, message", [
    ({"transform_matrix": "nan"}, "non-finite"),
    ({"transform_matrix": "singular"}, "not a rotation"),
    ({"transform_matrix": "scaled"}, "not a rotation"),
    ({"transform_matrix": "mirrored"}, "not a rotation"),
    ({"transform_matrix": "last_row"}, "last row"),
    ({"transform_matrix": [[1, 0, 0, "x"], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]}, "list of numbers"),
    ({"fl_x": 0.0}, "'fl_x' is 0.0, expected a finite number > 0"),
    ({"fl_x": float("nan")}, "'fl_x' is nan"),
    ({"fl_y": "500"}, "'fl_y' must be a number, got '500'"),
    ({"cx": None, "cy": float("inf")}, "'cy' is inf"),
])
def test_transforms_bad_cameras_are_refused_naming_file_and_frame(tmp_path, change, message):
    """Cameras that would fail later (a singular pose: LinAlgError in a later stage; a NaN
    or zero focal: non-finite renders) or be silently wrong (a scaled or mirrored rotation,
    a focal given as text) are refused when the scene is read, naming transforms.json and
    the frame."""
    meta = _transforms_fixture(tmp_path)
    f = meta["frames"][3]
    for k, v in change.items():
        if k == "transform_matrix" and isinstance(v, str):
            v = _pose_with(3, v)
        if v is None:
            f.pop(k)
        else:
            f[k] = v
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DataError, match=re.escape(message)) as info:
        read_transforms(tmp_path)
    text = str(info.value)
    assert "transforms.json" in text and "frame 3 (images/0003.png)" in text


def test_transforms_duplicate_frames_are_refused(tmp_path):
    meta = _transforms_fixture(tmp_path)
    meta["frames"][4]["file_path"] = "images/0001.png"
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DataError, match=r"frame 4 repeats frame 1's file_path 'images/0001.png'") as info:
        read_transforms(tmp_path)
    assert "transforms.json" in str(info.value)


def test_llff_count_mismatch(tmp_path):
    pb = np.zeros((3, 17))
    np.save(tmp_path / "poses_bounds.npy", pb)
    for i in range(2):
        _write_png(tmp_path / "images_8" / f"{i}.png", np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(DataError, match="2 images but poses_bounds.npy has 3 poses"):
        read_llff(tmp_path, downscale=8)
    with pytest.raises(DataError, match="unrecognised"):
        detect_format(tmp_path / "images_8")


# -- the two published copies of the NVOS LLFF scenes (docs/method.md §5) -----------------------------------
def _nerf_llff_data_fixture(root, n=4, W=160, H=120, k1=-0.05):
    """nerf_llff_data's layout: sparse/0 with one SIMPLE_RADIAL camera over full-resolution
    images/IMG_*.JPG, and images_4/ named image000.png ... (the same views, 1/4 size)."""
    sparse = root / "sparse" / "0"
    sparse.mkdir(parents=True)
    (sparse / "cameras.txt").write_text(f"1 SIMPLE_RADIAL {W} {H} 150.0 {W / 2 + 1.5} {H / 2 - 2.0} {k1}\n")
    lines = []
    for i in range(n):
        name = f"IMG_{4026 + i}.JPG"
        lines.append(f"{i + 1} 1 0 0 0 {0.2 * i} 0 3 1 {name}\n\n")
        img = np.full((H, W, 3), 20 * i, np.uint8)
        cv2.imwrite(str(_mkdir(root / "images") / name), img)
        _write_png(root / "images_4" / f"image{i:03d}.png", img[::4, ::4])
    (sparse / "images.txt").write_text("".join(lines))
    (sparse / "points3D.txt").write_text("1 0 0 1 200 100 50 0.5\n")


def _mkdir(p):
    p.mkdir(parents=True, exist_ok=True)
    return p


def test_nerf_llff_data_copy_reads_with_model_names_and_k1_dropped(tmp_path):
    _nerf_llff_data_fixture(tmp_path)
    scene = read_scene(tmp_path, downscale=4.0, test_every=0)
    assert [v.name for v in scene.train] == ["IMG_4026", "IMG_4027", "IMG_4028", "IMG_4029"]
    v = scene.train[1]
    assert v.path.endswith("images_4/image001.png") and v.image.shape == (30, 40, 3)
    assert float(v.image[0, 0, 0]) == pytest.approx(20 / 255, abs=1e-6)  # image001 = view 1
    # SIMPLE_RADIAL read as a pinhole (k1 dropped), scaled to the 1/4 images
    assert v.camera.fx == pytest.approx(150.0 / 4) and v.camera.fy == pytest.approx(150.0 / 4)
    assert v.camera.cx == pytest.approx((80 + 1.5) / 4) and v.camera.cy == pytest.approx((60 - 2.0) / 4)
    assert any("matched by sorted order" in n for n in scene.notes)
    assert any("SIMPLE_RADIAL" in n and "-0.05" in n and "dropped" in n for n in scene.notes)
    # full-size images: undistorted as before (no note about dropping)
    full = read_scene(tmp_path, downscale=1.0, test_every=0)
    c = full.train[0].camera
    assert not any("dropped" in n for n in full.notes) and (c.width, c.fx) != (160, 150.0)


def test_nerf_llff_data_mismatches_are_named(tmp_path):
    _nerf_llff_data_fixture(tmp_path)
    (tmp_path / "images_4" / "image003.png").unlink()
    with pytest.raises(DataError, match="3 images, the model 4") as info:
        read_scene(tmp_path, downscale=4.0, test_every=0)
    assert "images_4" in str(info.value)
    _write_png(tmp_path / "images_4" / "image003.png", np.zeros((40, 40, 3), np.uint8))
    with pytest.raises(DataError, match="another aspect or size") as info:
        read_scene(tmp_path, downscale=4.0, test_every=0)
    assert "image003.png" in str(info.value)
    with pytest.raises(DataError, match="distorted; undistortion needs the full-size images"):
        read_colmap(tmp_path, downscale=4.0, distortion="undistort")


def _nex_fixture(root, n=3, W=160, H=120, names=("IMG_4026", "IMG_4027", "IMG_4028")):
    """NeX's *_undistort layout: 14-column poses_bounds.npy + hwf_cxcy.npy, images/ full
    size and images_4/ named otherwise."""
    rows = []
    for i in range(n):
        R = np.eye(3)[:, [1, 0, 2]] * np.array([1, 1, -1])  # LLFF axes for an identity camera
        pose = np.concatenate([R, np.array([[0.1 * i], [0.0], [0.0]])], 1)
        rows.append(np.concatenate([pose.reshape(-1), [1.0, 10.0]]))
        img = np.full((H, W, 3), 30 * i, np.uint8)
        _write_png(root / "images" / f"{names[i]}.png", img)
        _write_png(root / "images_4" / f"image{i:03d}.png", img[::4, ::4])
    np.save(root / "poses_bounds.npy", np.stack(rows))
    np.save(root / "hwf_cxcy.npy", np.array([[H], [W], [140.0], [141.0], [W / 2 + 4.0], [H / 2 - 4.0]]))


def test_nex_undistort_layout(tmp_path):
    _nex_fixture(tmp_path)
    assert detect_format(tmp_path) == "llff"
    scene = read_llff(tmp_path, downscale=4, test_every=0)
    assert [v.name for v in scene.train] == ["IMG_4026", "IMG_4027", "IMG_4028"]
    c = scene.train[0].camera
    assert (c.width, c.height) == (40, 30)
    assert c.fx == pytest.approx(140.0 / 4) and c.fy == pytest.approx(141.0 / 4)
    assert c.cx == pytest.approx(84.0 / 4) and c.cy == pytest.approx(56.0 / 4)
    assert any("NeX" in n for n in scene.notes) and any("sorted order" in n for n in scene.notes)
    # LLFF axes: camera 1 sits 0.1 to the right of camera 0
    assert torch.allclose(scene.train[1].camera.center - scene.train[0].camera.center,
                          torch.tensor([0.1, 0.0, 0.0]), atol=1e-6)
    np.save(tmp_path / "hwf_cxcy.npy", np.array([120.0, 160.0, 140.0, 141.0, np.nan, 56.0]))
    with pytest.raises(DataError, match="non-finite intrinsics") as info:
        read_llff(tmp_path, downscale=4)
    assert "hwf_cxcy.npy" in str(info.value)
    (tmp_path / "hwf_cxcy.npy").unlink()
    with pytest.raises(DataError, match="needs hwf_cxcy.npy") as info:
        read_llff(tmp_path, downscale=4)
    assert "hwf_cxcy.npy" in str(info.value)


# -- nerfstudio's distortion keys and initial point cloud ----------------------------------------
def _lens_transforms(root, model, dist, W=80, H=60):
    """transforms.json frames whose images show a blob where a 3D point lands through the
    given lens (COLMAP's model of the same name projects it)."""
    import pycolmap

    point = np.array([2.5, -0.9, 0.1])  # near the edge of a wide view: k3 moves it by pixels
    colmap_model, params = {
        "OPENCV": ("FULL_OPENCV", [dist.get("k1", 0), dist.get("k2", 0), dist.get("p1", 0),
                                   dist.get("p2", 0), dist.get("k3", 0), 0, 0, 0]),
        "OPENCV_FISHEYE": ("OPENCV_FISHEYE", [dist.get(k, 0) for k in ("k1", "k2", "k3", "k4")]),
    }[model]
    cam = pycolmap.Camera.create_from_model_name(1, colmap_model, 1.0, W, H)
    cam.params = [40.0, 41.0, 40.5, 29.5] + [float(p) for p in params]
    frames = []
    for i, tz in enumerate((3.0, 3.3, 2.8)):
        c2w_cv = np.eye(4)
        c2w_cv[:3, 3] = [0.1 * i, 0.0, -tz]
        u, v = cam.img_from_cam((point - c2w_cv[:3, 3])[None])[0]
        yy, xx = np.mgrid[0:H, 0:W] + 0.5
        blob = np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * 1.2**2))
        _write_png(root / "images" / f"{i:04d}.png",
                   np.round(np.stack([blob, 0.5 * blob, np.full_like(blob, 0.2)], 2) * 255).astype(np.uint8))
        c2w_gl = c2w_cv @ np.diag([1.0, -1.0, -1.0, 1.0])
        frames.append({"file_path": f"images/{i:04d}.png", "transform_matrix": c2w_gl.tolist()})
    meta = {"camera_model": model, "fl_x": 40.0, "fl_y": 41.0, "cx": 40.5, "cy": 29.5, "w": W, "h": H,
            "frames": frames, **dist}
    (root / "transforms.json").write_text(json.dumps(meta))
    return point


@pytest.mark.parametrize("model, dist", [
    ("OPENCV", {"k1": -0.2, "k2": 0.05, "k3": 0.1, "p1": 0.001}),
    ("OPENCV_FISHEYE", {"k1": 0.05, "k2": -0.01, "k3": 0.002, "k4": -0.001}),
], ids=["opencv with k3", "fisheye k1..k4"])
def test_transforms_distortion_terms_are_applied(tmp_path, model, dist):
    point = _lens_transforms(tmp_path, model, dist)

    def worst_px(scene):
        return max(float(np.abs(_blob_centre(v.image) - v.camera.project(
            torch.from_numpy(point[None]).float())[0][0].numpy()).max()) for v in scene.train)

    # undistorted: the blob lands where the pinhole camera projects it (measured <= 0.18 px)
    assert worst_px(read_transforms(tmp_path, test_every=0)) < 0.3
    if model == "OPENCV":  # negative control: the same lens without its k3 misses by pixels
        meta = json.loads((tmp_path / "transforms.json").read_text())
        meta.pop("k3")
        (tmp_path / "transforms.json").write_text(json.dumps(meta))
        assert worst_px(read_transforms(tmp_path, test_every=0)) > 1.0  # measured 1.9


@pytest.mark.parametrize("change, key", [
    ({"camera_model": "OPENCV", "k4": 0.01}, "k4"),
    ({"camera_model": "OPENCV", "distortion_params": [0.1, 0, 0, 0, 0, 0]}, "distortion_params"),
    ({"camera_model": "PINHOLE", "k1": -0.1}, "k1"),
    ({"camera_model": "OPENCV_FISHEYE", "p1": 0.01}, "p1"),
    ({"camera_model": "OPENCV", "k1": "strong"}, "k1"),  # not a number
    ({"camera_model": "OPENCV", "k2": float("nan")}, "k2"),
    ({"camera_model": "OPENCV", "distortion_params": 0.1}, "distortion_params"),  # not a list
])
def test_transforms_distortion_the_model_cannot_hold_is_refused(tmp_path, change, key):
    _lens_transforms(tmp_path, "OPENCV", {})
    meta = json.loads((tmp_path / "transforms.json").read_text())
    meta.update(change)
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DataError, match=key) as info:
        read_transforms(tmp_path)
    assert "transforms.json" in str(info.value)


def test_transforms_ply_file_path_gives_the_initial_points(tmp_path):
    from plyfile import PlyData, PlyElement

    _lens_transforms(tmp_path, "OPENCV", {})
    pts = np.zeros(3, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"),
                             ("blue", "u1")])
    pts["x"], pts["red"] = [1, 2, 3], [255, 0, 51]
    PlyData([PlyElement.describe(pts, "vertex")]).write(str(tmp_path / "sparse_pc.ply"))
    meta = json.loads((tmp_path / "transforms.json").read_text())
    meta["ply_file_path"] = "sparse_pc.ply"
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    scene = read_transforms(tmp_path)
    assert torch.equal(scene.points[:, 0], torch.tensor([1.0, 2, 3]))
    assert torch.allclose(scene.points_rgb[:, 0], torch.tensor([1.0, 0.0, 0.2]))
    assert any("sparse_pc.ply" in n for n in scene.notes)
    meta["ply_file_path"] = "missing.ply"
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DataError, match="missing.ply"):
        read_transforms(tmp_path)


def test_blender_test_views_that_reuse_training_names_are_kept_apart(tmp_path):
    """The published NeRF-synthetic splits reuse names (train/r_0, test/r_0 are different
    images); the held-out views get their own names, so none is trained on or lost."""
    import math as _math

    from cobgs.data.blender import read_blender

    for split, shade in (("train", 60), ("test", 200)):
        frames = []
        for k in range(3):
            img = np.zeros((24, 32, 4), np.uint8)
            img[..., :3] = shade + k
            img[8:16, 8:20, 3] = 255
            _write_png(tmp_path / split / f"r_{k}.png", img)
            c2w = np.eye(4)
            c2w[:3, 3] = [0.3 * k, 0.0, 4.0]
            frames.append({"file_path": f"./{split}/r_{k}", "transform_matrix": c2w.tolist()})
        (tmp_path / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": _math.radians(50),
                                                                         "frames": frames}))
    scene = read_blender(tmp_path)
    train, test = [v.name for v in scene.train], [v.name for v in scene.test]
    assert train == ["r_0", "r_1", "r_2"] and test == ["test_r_0", "test_r_1", "test_r_2"]
    assert not set(train) & set(test) and all(v.camera.name == v.name for v in scene.test)
    # the test images themselves (inside the alpha: grey 200 vs the training views' 60)
    assert float(scene.test[0].image[10, 10].mean()) > 0.5 > float(scene.train[0].image[10, 10].mean())
