"""Click files (cobgs.masks.clicks) and multi-frame click propagation through the stand-in SAM2."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cobgs.errors import InputError
from cobgs.masks.api import FramePrompt, generate_masks_from_clicks
from cobgs.masks.clicks import OWN, SAGA, read_clicks, to_image_pixels

from . import scenes

# The published file's structure (openvdb/fvdb-examples, garfvdb/evaluation/
# saga_v2_input_points.json): metadata keys with "_", quarter-resolution values, _scale 4.
SAGA_FILE = {
    "_comment": "SAGA v2 input points for NVOS evaluation.",
    "_scale": 4,
    "horns": [[450, 300], [480, 500]],
    "horns_left": [[150, 400], [54, 546], [21, 496]],
    "fern": [[533, 367]],
}


def _write(tmp_path, data, name="clicks.json"):
    p = tmp_path / name
    p.write_text(json.dumps(data) if not isinstance(data, str) else data)
    return p


def test_saga_v2_layout_scaled_and_looked_up_as_the_community_does(tmp_path):
    f = read_clicks(_write(tmp_path, SAGA_FILE))
    assert f.layout == SAGA and f.scale == 4 and set(f.objects) == {"horns", "horns_left", "fern"}
    fern = f.lookup(["fern"])
    assert fern.layout == SAGA and len(fern.frames) == 1 and fern.frames[0].frame == ""
    np.testing.assert_array_equal(fern.frames[0].points, [[2132.0, 1468.0]])  # value x _scale
    assert fern.frames[0].labels.tolist() == [1]
    # exact first, then without _undistort, then the name before the first "_"
    assert f.lookup(["horns_left"]).key == "horns_left"
    assert f.lookup(["horns_center"]).key == "horns"
    assert f.lookup(["fern_undistort"]).key == "fern"
    with pytest.raises(InputError, match=r"clicks\.json: no entry for 'trex'.*'fern'"):
        f.lookup(["trex"])
    # no _scale: 1
    assert read_clicks(_write(tmp_path, {"fern": [[1, 2]]}, "s1.json")).lookup(["fern"]).frames[0].points.tolist() \
        == [[1.0, 2.0]]


def test_per_object_layout(tmp_path):
    data = {"image_size": [64, 48], "objects": {
        "square": {"frames": {"0001": {"positive": [[20, 20], [22, 18]], "negative": [[2, 2]]},
                              "0004": {"positive": [[30, 25]]}}},
        "other": {"image_size": [128, 96], "frames": {"0002": {"positive": [[100, 90]]}}}}}
    f = read_clicks(_write(tmp_path, data))
    sq = f.lookup(["square"])
    assert f.layout == OWN and sq.image_size == (64, 48) and [fr.frame for fr in sq.frames] == ["0001", "0004"]
    assert sq.frames[0].labels.tolist() == [1, 1, 0] and sq.frames[0].num_positive == 2
    assert f.lookup(["other"]).image_size == (128, 96)  # the object's own wins
    # own-layout keys match exactly only (no SAGA-style fallbacks)
    with pytest.raises(InputError, match="no entry"):
        f.lookup(["square_noisy"])
    np.testing.assert_allclose(to_image_pixels(np.array([[100.0, 90.0]]), (128, 96), (64, 48)), [[50.0, 45.0]])


@pytest.mark.parametrize("data, match", [
    ("{not json", r"bad\.json: not valid JSON"),
    ([1, 2], "expected a JSON object"),
    ({"_scale": 4}, "no entry"),
    ({"_scale": -1, "fern": [[1, 2]]}, r"_scale: must be a positive number"),
    ({"fern": [[1, 2, 3]]}, r"entry 'fern': clicks point 0 must be \[x, y\]"),
    ({"fern": [[1, "a"]]}, r"entry 'fern': clicks point 0"),
    ({"fern": [[-1, 2]]}, r"entry 'fern': clicks point 0 must be finite and >= 0"),
    ({"fern": []}, r"entry 'fern': no click"),
    ({"objects": {"mug": {"frames": {"IMG_1": {"positive": [[1, 2]], "negativ": []}}}}},
     r"object 'mug', frame 'IMG_1': unknown key\(s\) \['negativ'\]"),
    ({"objects": {"mug": {"frames": {"IMG_1": {"negative": [[1, 2]]}}}}},
     r"object 'mug', frame 'IMG_1': needs at least one positive click"),
    ({"objects": {"mug": {"frames": {"IMG_1": {"positive": [[1e400, 2]]}}}}},
     r"object 'mug', frame 'IMG_1': positive point 0 must be finite"),
    ({"objects": {"mug": {"image_size": [10, 10], "frames": {"IMG_7": {"positive": [[11, 2]]}}}}},
     r"object 'mug', frame 'IMG_7': positive click \[11.0, 2.0\] lies outside image_size \[10, 10\]"),
    ({"objects": {"mug": {"frames": {}}}}, r"object 'mug': frames must map frame names"),
    ({"objects": {"mug": [[1, 2]]}}, r"object 'mug': must be"),
    ({"objects": {"mug": {"image_size": [0, 3], "frames": {"a": {"positive": [[1, 1]]}}}}},
     r"object 'mug': image_size must be \[width, height\]"),
    ({"objects": {}, "extra": 1}, r"top level: unknown key"),
])
def test_bad_click_files_name_file_object_and_frame(tmp_path, data, match):
    p = _write(tmp_path, data, "bad.json")
    with pytest.raises(InputError, match=match) as err:
        read_clicks(p)
    assert str(p) in str(err.value)


def test_missing_click_file(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        read_clicks(tmp_path / "nope.json")


# -- propagation ------------------------------------------------------------------------
@pytest.fixture(scope="module")
def drifting(tmp_path_factory):
    """8 frames of a red square drifting right and down."""
    return scenes.write_sequence(tmp_path_factory.mktemp("drift"),
                                 [scenes.Frame("red", x=6 + 5 * i, y=8 + 2 * i) for i in range(8)])


def test_clicks_on_two_frames_condition_both_and_name_masks_after_views(models_dir, drifting, tmp_path):
    paths, gts = drifting
    names = [f"IMG_{i:04d}" for i in range(len(paths))]
    centre = lambda gt: np.argwhere(gt).mean(0)[::-1]  # noqa: E731  (x, y)
    prompts = [FramePrompt(5, centre(gts[5])[None], np.array([1.0])),
               FramePrompt(2, np.stack([centre(gts[2]), [1.0, 1.0]]), np.array([1.0, 0.0]))]
    res = generate_masks_from_clicks(paths, prompts, models_dir, tmp_path / "out", names=names)
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == sorted(f"{n}.png" for n in names)
    # both prompted frames condition; the others are tracked (backward before frame 2)
    assert res.sources == ["propagated"] * 2 + ["prompt", "propagated", "propagated", "prompt"] + ["propagated"] * 2
    import cv2

    for i, gt in enumerate(gts):
        m = cv2.imread(str(tmp_path / "out" / f"{names[i]}.png"), cv2.IMREAD_GRAYSCALE) > 127
        assert scenes.iou(m, gt) > 0.8, i
    log = json.loads(res.log_path.read_text())
    assert [p["stem"] for p in log["prompts"]] == ["IMG_0002", "IMG_0005"]
    assert log["prompts"][0]["labels"] == [1, 0] and log["prompt_frame"] == 2
    assert log["frames"][0]["stem"] == "IMG_0000" and log["frames"][0]["image"] == "0000.png"


def test_click_prompts_are_checked(models_dir, drifting, tmp_path):
    paths, _ = drifting
    p = FramePrompt(1, np.array([[20.0, 20.0]]), np.array([1.0]))
    with pytest.raises(InputError, match="more than one prompt for frame"):
        generate_masks_from_clicks(paths, [p, p], models_dir, tmp_path / "o")
    with pytest.raises(InputError, match="prompt frame must be in"):
        generate_masks_from_clicks(paths, [FramePrompt(99, p.points, p.labels)], models_dir, tmp_path / "o")
    with pytest.raises(InputError, match="one name per image"):
        generate_masks_from_clicks(paths, [p], models_dir, tmp_path / "o", names=["a"])
    with pytest.raises(InputError, match="plain file names"):
        generate_masks_from_clicks(paths, [p], models_dir, tmp_path / "o",
                                   names=[f"../x{i}" for i in range(len(paths))])
