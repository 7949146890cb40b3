"""SPIn-NeRF's annotation release (issue 61): the reader on the published layout, what it refuses,
and the protocol's scores against the peers' released evaluation, reimplemented from their
formulas (SA3D lib/evaluate.py: one IoU over the stacked masks; LUDVIG
evaluation/spin_nvos/segmentation.py: the mean of per-view IoUs over the sorted masks but the
first)."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from cobgs.data.spin import SPIN_SCENES, read_spin_scene
from cobgs.errors import DataError

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "stages"))
from protocol_fixtures import spin_published  # noqa: E402


@pytest.fixture(scope="module")
def release(tmp_path_factory):
    """The whole release, RGB stand-ins for every runnable scene (no synthetic scene)."""
    root, rgb = spin_published(tmp_path_factory.mktemp("spin"), {})
    return root, rgb


def _views(rgb: Path) -> dict:
    files = sorted((rgb / "images").iterdir())
    return {f.stem: f for f in files}


def _read(root, rgb, scene, **kw):
    from cobgs.data.spin import image_size

    views = _views(rgb[scene])
    return read_spin_scene(root, scene, list(views), view_size=lambda v: image_size(views[v]), **kw)


def test_every_scene_maps_as_published(release):
    root, rgb = release
    assert sorted(p.name for p in root.iterdir() if p.is_dir()) == sorted(v[0] for v in SPIN_SCENES.values())
    for scene, (_, count, rule) in SPIN_SCENES.items():
        if scene == "fork":
            continue  # (no RGB)
        s = _read(root, rgb, scene)
        assert len(s.masks) == count and s.rule == rule
        assert s.prompt == min(s.masks, key=lambda v: s.mask_names[v]) and s.prompt not in s.scored
        assert len(s.scored) == count - 1
        views = sorted(_views(rgb[scene]))
        for v, name in s.mask_names.items():
            stem = Path(name).stem
            if rule == "index":
                assert views[int(stem[5:])] == v
            elif rule == "prefix" and stem[:2] in ("0_", "1_") and stem not in views:
                assert stem[2:] == v
            else:
                assert stem == v
    orchids = _read(root, rgb, "orchids")
    views = sorted(_views(rgb["orchids"]))
    assert views[14] not in orchids.masks and views[15] in orchids.masks  # sparse: image015 after image013
    lego = _read(root, rgb, "lego")
    assert {n[:2] for n in lego.mask_names.values()} == {"0_", "1_"}


def _copy(release, tmp_path):
    root, rgb = release
    dst = tmp_path / root.name
    shutil.copytree(root, dst)
    return dst, rgb


def test_a_missing_scene_is_refused_naming_the_folder(release, tmp_path):
    root, rgb = _copy(release, tmp_path)
    shutil.rmtree(root / "room (llff)")
    with pytest.raises(DataError, match=r"no folder 'room \(llff\)'"):
        _read(root, rgb, "room")


def test_an_extra_file_is_refused_naming_it(release, tmp_path):
    root, rgb = _copy(release, tmp_path)
    (root / "fern (llff)" / "notes.txt").write_text("mine")
    with pytest.raises(DataError, match="notes.txt: not a file of the SPIn-NeRF release"):
        _read(root, rgb, "fern")
    (root / "fern (llff)" / "notes.txt").unlink()
    shutil.copy(root / "fern (llff)" / "image003.png", root / "fern (llff)" / "image003 (1).png")
    with pytest.raises(DataError, match=r"image003 \(1\).png.*not imageNNN"):
        _read(root, rgb, "fern")


def test_a_renamed_mask_is_refused_naming_it(release, tmp_path):
    root, rgb = _copy(release, tmp_path)
    d = root / "room (llff)"
    first = sorted(p for p in d.iterdir() if not p.stem.endswith(("_pseudo", "_cutout")) and p.suffix == ".png")[0]
    first.rename(d / "DJI_renamed.png")
    with pytest.raises(DataError, match="_(pseudo|cutout).png has no GT mask"):
        _read(root, rgb, "room")
    for comp in ("_pseudo", "_cutout"):
        (d / f"{first.stem}{comp}.png").rename(d / f"DJI_renamed{comp}.png")
    with pytest.raises(DataError, match="DJI_renamed.png: mask 'DJI_renamed' names no view"):
        _read(root, rgb, "room")
    # fewer masks than the release has: refused as incomplete
    root2, _ = _copy(release, tmp_path / "b")
    for p in (root2 / "fern (llff)").glob("image019*"):
        p.unlink()
    with pytest.raises(DataError, match="19 GT masks, the release has 20"):
        _read(root2, rgb, "fern")


def test_a_mask_of_the_wrong_size_is_refused_naming_it(release, tmp_path):
    root, rgb = _copy(release, tmp_path)
    f = root / "truck (Tanks & Temples)".replace("truck", "Truck") / "000001.png"
    if not f.is_file():
        f = sorted((root / "Truck (Tanks & Temples)").glob("0_*.png"))[0]
    m = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
    cv2.imwrite(str(f), cv2.resize(m, (m.shape[1] // 2, m.shape[0]), interpolation=cv2.INTER_NEAREST))
    with pytest.raises(DataError, match=f"{f.name}: mask is 20x30, its view's image is 40x30"):
        _read(root, rgb, "truck")
    # one pixel wider (the published Truck masks are 980x546 over 979x546 RGB): read
    cv2.imwrite(str(f), np.pad(m, ((0, 0), (0, 1))))
    assert len(_read(root, rgb, "truck").masks) == 65


def test_a_prefixed_and_plain_name_for_one_view_is_ambiguous(tmp_path):
    from cobgs.data.spin import _match

    with pytest.raises(DataError, match="names two views"):
        _match("prefix", "0_00012", ["00012", "0_00012"], tmp_path / "0_00012.png")
    assert _match("prefix", "1_00012", ["00012", "00013"], tmp_path / "x.png") == "00012"
    with pytest.raises(DataError, match="names no view"):
        _match("stem", "1_00012", ["00012"], tmp_path / "x.png")  # only truck and lego strip a prefix


# -- the peers' scoring, from their formulas --------------------------------------------------------
def _sa3d_pooled_iou(preds: np.ndarray, gts: np.ndarray) -> float:
    """SA3D lib/evaluate.py cal_IoU on stacked bool masks: |a == b and a != 0| / |a + b != 0|."""
    inter = np.count_nonzero(np.logical_and(preds == gts, preds != 0))
    return inter / np.count_nonzero(preds.astype(np.int64) + gts.astype(np.int64))


def _ludvig_mean_iou(names: list, preds: dict, gts: dict) -> float:
    """LUDVIG: the masks sorted by name, each view's IoU, the mean over all but the first."""
    res = []
    for i, n in enumerate(sorted(names)):
        p, g = preds[n], gts[n]
        iou = np.logical_and(p, g).sum() / np.logical_or(p, g).sum()
        if i > 0:
            res.append(iou)
    return sum(res) / len(res)


def test_scores_equal_the_peers_evaluation_to_4_decimals():
    from cobgs.evaluate.protocols import spin_scores

    rng = np.random.default_rng(7)
    names = [f"image{i:03d}" for i in (0, 1, 2, 3, 5, 8)]
    gts, preds, preds_small = {}, {}, {}
    for k, n in enumerate(names):
        g = np.zeros((48, 64), np.uint8)
        cv2.ellipse(g, (30 + k, 24), (14 + k, 9), 10.0 * k, 0, 360, 255, -1)
        p = (g > 0) ^ (rng.random(g.shape) < 0.04)
        gts[n], preds[n] = g, p
        preds_small[n] = cv2.resize(p.astype(np.uint8) * 255, (32, 24), interpolation=cv2.INTER_NEAREST)
    r = spin_scores(preds, gts, prompt=names[0])
    gb = {n: gts[n] > 127 for n in names}
    assert r["views"] == len(names) - 1 and names[0] not in r["per_view"]
    assert round(r["iou"], 4) == round(_ludvig_mean_iou(names, preds, gb), 4)
    scored = names[1:]
    pooled = _sa3d_pooled_iou(np.stack([preds[n] for n in scored]), np.stack([gb[n] for n in scored]))
    assert round(r["iou_pooled"], 4) == round(pooled, 4) and r["iou_pooled"] != pytest.approx(r["iou"], abs=1e-6)
    acc = np.mean([(preds[n] == gb[n]).mean() for n in scored])
    assert round(r["acc"], 4) == round(acc, 4)
    # a 0/1 GT reads as the 0/255 one; a prediction at another size is resized NEAREST to the GT's
    r01 = spin_scores(preds, {n: (g > 0).astype(np.uint8) for n, g in gts.items()}, prompt=names[0])
    assert r01["iou"] == r["iou"]
    small = spin_scores(preds_small, gts, prompt=names[0])
    assert all(v["resized"] for v in small["per_view"].values()) and 0.5 < small["iou"] < 1.0
