"""Mask routes behind one registry (issue 58 item 3): a new route is one class and one line of
``cobgs.masks.sources.SOURCES``; the stage, its params' choices and its cache key read it there."""

from __future__ import annotations

import io

import numpy as np

from cobgs.masks.sources import SOURCES, MaskSource
from pipeline import RunOptions, load_workflow, run_workflow
from stages.registry import load_registry

TOML = """
[workflow]
nested = { object = "scene" }
[params.dataset]
preset = "demo"
num_views = 8
width_px = 64
height_px = 48
[params.masks]
source = "left_half"
[axes.scene.s]
kind = "synthetic"
[axes.method.cobgs]
[axes.object.s.ball]
"""


class LeftHalf(MaskSource):
    """A route of its own: the left half of every training view (what a new route writes)."""

    name, reads = "left_half", ("files_threshold",)

    def route(self, from_folder):
        return "the left half"

    def masks(self, req):
        out = {}
        for v in req.views:
            m = np.zeros((v.height, v.width), np.uint8)
            m[:, : v.width // 2] = 255
            out[v.name] = m
        return out, {"note": "half"}


def test_a_new_mask_source_is_one_class_and_one_registry_line(tmp_path, monkeypatch):
    monkeypatch.setitem(SOURCES, "left_half", LeftHalf())  # the one line
    path = tmp_path / "w.toml"
    path.write_text(TOML)
    out = io.StringIO()
    wf = load_workflow(path, load_registry())
    summary = run_workflow(wf, RunOptions(cache_dir=tmp_path / "c", only=("dataset", "sfm", "masks")), stream=out)
    assert summary.exit_code == 0, out.getvalue()
    task = next(t for t in summary.plan.tasks if t.stage.name == "masks")
    assert task.stage.key_params(task.params.value, task.params.json) == {"source": "left_half", "files_threshold": 0}
    from pipeline import entries

    rec = next(r for r in entries(wf, tmp_path / "c") if r.stage == "masks")
    folder = rec.output("masks")
    import json

    info = json.loads((folder / "masks.json").read_text())
    assert info["route"] == "the left half" and info["note"] == "half" and info["views"] == len(info["area_px"]) > 0
    import cv2

    m = cv2.imread(str(next(folder.glob("*.png"))), cv2.IMREAD_GRAYSCALE)
    assert m[:, : m.shape[1] // 2].min() == 255 and m[:, m.shape[1] // 2:].max() == 0


def test_each_route_keys_only_what_it_reads():
    from stages.masks import STAGE, MasksParams
    from pipeline.params import to_json

    for name, route in SOURCES.items():
        if route.models or name == "points":
            continue  # (their params need a model folder / click file to build; their keys: test_params)
        p = MasksParams(source=name)
        key = STAGE.key_params(p, to_json(p))
        assert set(key) == {"source", *route.reads}, name
