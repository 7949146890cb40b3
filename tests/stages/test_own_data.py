"""Your own photos end to end, as a new user runs them: `cobgs new` on a folder of photos
taken through a real lens (distortion) with masks made for those photos and no ground
truth; SfM with COLMAP's default camera model, the masks undistorted like the images,
training, COB-GS, warnings, export, and a report that builds and loads in a browser
without an error or a broken image."""

from __future__ import annotations

import io
import json
import math
from pathlib import Path

import pytest

from own_data_fixture import make  # tests/stages is on sys.path
from pipeline import RunOptions, entries, load_workflow, run_workflow
from stages.registry import load_registry

# The short training of the e2e tests, as --set overrides of what `cobgs new` wrote.
SHORT = ["train.iterations=500", "train.scale_schedule=false", "train.densify_from_its=50",
         "train.densify_until_its=350", "train.densify_interval_its=50",
         "train.opacity_reset_interval_its=1000", "train.position_lr_decay_its=500",
         "train.sh_degree_interval_its=100", "train.max_gaussians=6000",
         "refine.cobgs.stage_length_views=2.0", "refine.cobgs.mask_stages=3"]


@pytest.fixture(scope="module")
def own(tmp_path_factory):
    """The own-data flow as a user runs it: `cobgs new` on the photo folder, then the
    workflow it wrote (COLMAP's default camera, masks from files), shortened with --set."""
    from stages.commands.cli import main

    root = tmp_path_factory.mktemp("own")
    photos = make(root)
    path = root / "photos.toml"
    assert main(["new", str(photos), "--out", str(path)]) == 0
    text = path.read_text()
    assert 'kind = "images"' in text and 'source = "files"' in text and 'camera_model = "SIMPLE_RADIAL"' in text
    wf = load_workflow(path, load_registry(), SHORT)
    out = io.StringIO()
    summary = run_workflow(wf, RunOptions(cache_dir=root / "cache", package_version="test"), stream=out)
    assert summary.exit_code == 0, out.getvalue()
    return root, path, wf, {(r.stage, r.item.id): r for r in entries(wf, root / "cache")}


def test_stages_too_short_for_a_label_to_reach_the_foreground_warn_on_the_refine_task(own):
    """Stages shorter than the 22 MASK iterations a split child's label needs to pass 0.9
    (docs/method.md §2, "Few views") are a warning on the refine task with the setting that
    suffices; the run as written (2 x 14 views = 28) has none."""
    root, path, _, recs = own
    views = json.loads((recs[("refine", "photos/cobgs/ball")].output("refined") / "refine.json").read_text())["train_views"]
    assert 2 * views >= 22
    assert not (recs[("refine", "photos/cobgs/ball")].manifest.get("extra") or {}).get("warnings")
    sets = [s for s in SHORT if not s.startswith("refine.cobgs.stage_length_views")] + \
        ["refine.cobgs.stage_length_views=1.0"]
    wf = load_workflow(path, load_registry(), sets)
    out = io.StringIO()
    opts = RunOptions(cache_dir=root / "cache", package_version="test", only=("refine",), items="photos/cobgs/*")
    assert run_workflow(wf, opts, stream=out).exit_code == 0, out.getvalue()
    rec = {(r.stage, r.item.id): r for r in entries(wf, root / "cache")}[("refine", "photos/cobgs/ball")]
    warns = (rec.manifest.get("extra") or {}).get("warnings") or []
    want = f"stages of {views} iterations (1 x {views} views)"
    assert any(w.startswith(want) and f"stage_length_views >= {math.ceil(220 / views) / 10:g}" in w
               for w in warns), warns
    assert "WARNING: " + want in out.getvalue()


def test_masks_made_for_the_photos_are_undistorted_like_them(own):
    import cv2
    import numpy as np
    import pycolmap

    root, _, _, recs = own
    sfm = recs[("sfm", "photos")].output("poses")
    info = json.loads((sfm / "sfm.json").read_text())["undistorted_masks"]
    n_masks = len(list((root / "photos" / "masks" / "ball").iterdir()))
    assert info["masks"] == n_masks and info["objects"] == ["ball"]
    cam = pycolmap.Reconstruction(str(sfm / "sparse" / "0")).cameras[1]
    assert (cam.width, cam.height) != (320, 240)  # the undistorted images changed size
    masks = recs[("masks", "photos/ball")].output("masks")
    tf = json.loads((root / "synth" / "transforms.json").read_text())
    fx, fy, cx, cy = cam.params
    ys, xs = np.mgrid[0:cam.height, 0:cam.width].astype(np.float32)
    map_x = ((xs + 0.5 - cx) / fx * tf["fl_x"] + tf["cx"] - 0.5).astype(np.float32)
    map_y = ((ys + 0.5 - cy) / fy * tf["fl_y"] + tf["cy"] - 0.5).astype(np.float32)
    ious = []
    for f in sorted(masks.glob("*.png")):
        m = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        assert m.shape == (cam.height, cam.width) and set(np.unique(m)) <= {0, 255}
        exact = cv2.imread(str(root / "synth" / "masks" / "ball" / f.name), cv2.IMREAD_GRAYSCALE)
        exact = cv2.remap(exact, map_x, map_y, cv2.INTER_NEAREST) > 127  # the pinhole truth, seen by the undistorted camera
        ious.append(((m > 127) & exact).sum() / ((m > 127) | exact).sum())
    # Measured 0.98-0.99 (SfM's own estimate of the lens); the distorted masks taken as they
    # are would not even have the images' size.
    assert min(ious) > 0.95, ious


def test_the_report_builds_and_loads_cleanly_without_ground_truth(own, tmp_path):
    from stages.commands.report import build_report

    root, path, _, recs = own
    index = build_report(path, out_dir=tmp_path / "report", cache_dir=root / "cache", sets=SHORT)
    html = index.read_text()
    assert "photos" in html and "ball" in html
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "reports"))
    from report_browser import CHROMIUM, Browser

    if not Path(CHROMIUM).exists():
        pytest.skip(f"{CHROMIUM} missing: `make test` installs it when run as root")
    with Browser() as b:
        b.goto(index.resolve().as_uri())
        assert b.eval("document.documentElement.getAttribute('data-report-ready')") == "1"
        assert b.errors() == []
        broken = b.eval("Array.from(document.images).filter(i => !(i.complete && i.naturalWidth > 0))"
                        ".map(i => i.getAttribute('src'))")
        assert broken == [] and b.eval("document.images.length") > 3


def test_a_psnr_drop_beyond_the_margin_is_a_warning_everywhere(own, tmp_path):
    """A refined scene whose held-out PSNR falls by more than evaluate.warn_psnr_drop_db
    below the vanilla scene's is a warning on the console line, in summary.json /
    summary.csv, in `cobgs export`'s printout and as a banner in the report, naming the
    setting to try; under the margin there is none."""
    import io

    from stages.commands.report import build_report

    root, path, wf, recs = own
    # The authors' released RAEM prunes every ambiguous Gaussian: the PSNR drop this test needs
    # (measured 0.7 dB here; the default, paper RAEM, leaves the PSNR where it was)
    sets0 = SHORT + ["refine.cobgs.raem=released"]
    wf0 = load_workflow(path, load_registry(), sets0)
    assert run_workflow(wf0, RunOptions(cache_dir=root / "cache", package_version="test"),
                        stream=io.StringIO()).exit_code == 0
    rec0 = {(r.stage, r.item.id): r for r in entries(wf0, root / "cache")}[("evaluate", "photos/cobgs/ball")]
    row = json.loads((rec0.output("metrics") / "metrics.json").read_text())["row"]
    drop = row["psnr_vanilla"] - row["psnr"]
    assert "warnings" not in row  # the default margin (2 dB) is not crossed here
    assert drop > 0, f"the released RAEM left the held-out PSNR unchanged ({drop:.2f} dB)"
    sets = sets0 + [f"evaluate.warn_psnr_drop_db={drop / 2}"]
    wf2 = load_workflow(path, load_registry(), sets)
    out = io.StringIO()
    summary = run_workflow(wf2, RunOptions(cache_dir=root / "cache", package_version="test"), stream=out)
    assert summary.exit_code == 0
    log = out.getvalue()
    assert "WARNING: the refined scene's held-out PSNR" in log and 'refine.cobgs.raem = "off"' in log
    recs2 = {(r.stage, r.item.id): r for r in entries(wf2, root / "cache")}
    summ = recs2[("summary", "")].output("summary")
    assert [w["item"] for w in json.loads((summ / "summary.json").read_text())["warnings"]] == ["photos/cobgs/ball"]
    assert "warning" in (summ / "summary.csv").read_text().splitlines()[0].split(",")
    index = build_report(path, out_dir=tmp_path / "report", cache_dir=root / "cache", sets=sets)
    assert "Warning — photos / cobgs / ball" in index.read_text()
    from stages.commands.cli import main

    import contextlib

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        main(["export", str(path), "--cache-dir", str(root / "cache"), "--to", str(tmp_path / "out")]
             + [a for s in sets for a in ("--set", s)])
    assert "WARNING photos/cobgs/ball" in buf.getvalue() and "mIoU n/a: the held-out views have no" in buf.getvalue()
