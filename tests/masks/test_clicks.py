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
    with pytest.raises(InputError, match=r"no object for 'square_noisy' \(object keys in the file"):
        f.lookup(["square_noisy"])
    np.testing.assert_allclose(to_image_pixels(np.array([[100.0, 90.0]]), (128, 96), (64, 48)), [[50.0, 45.0]])


@pytest.mark.parametrize("data, match", [
    ("{not json", r"bad\.json: not valid JSON"),
    ([1, 2], "expected a JSON object"),
    ({"_scale": 4}, "no entry"),
    ({"_scale": -1, "fern": [[1, 2]]}, r"_scale: must be a number in \(0, 1024\]"),
    ({"fern": [[1, 2, 3]]}, r"entry 'fern': clicks point 0 must be \[x, y\]"),
    ({"fern": [[1, "a"]]}, r"entry 'fern': clicks point 0"),
    ({"fern": [[-1, 2]]}, r"entry 'fern': clicks point 0 must be two finite pixel coordinates in \[0, 1048576\)"),
    ({"fern": []}, r"entry 'fern': no click"),
    ({"objects": {"mug": {"frames": {"IMG_1": {"positive": [[1, 2]], "negativ": []}}}}},
     r"object 'mug', frame 'IMG_1': unknown key\(s\) \['negativ'\]"),
    ({"objects": {"mug": {"frames": {"IMG_1": {"negative": [[1, 2]]}}}}},
     r"object 'mug', frame 'IMG_1': needs at least one positive click"),
    ({"objects": {"mug": {"frames": {"IMG_1": {"positive": [[1e400, 2]]}}}}},
     r"object 'mug', frame 'IMG_1': positive point 0 must be two finite pixel coordinates"),
    # Issue 44 M2: a huge integer (OverflowError in math.isfinite) and a huge image_size
    ({"objects": {"mug": {"frames": {"IMG_1": {"positive": [[10 ** 400, 2]]}}}}},
     r"object 'mug', frame 'IMG_1': positive point 0 must be two finite pixel coordinates .*<401-digit integer>"),
    ({"fern": [[10 ** 400, 2]]}, r"entry 'fern': clicks point 0 must be two finite pixel coordinates"),
    ({"objects": {"mug": {"image_size": [10 ** 400, 5], "frames": {"a": {"positive": [[1, 1]]}}}}},
     r"object 'mug': image_size must be \[width, height\] \(two integers in 1..1048576\), got \[<401-digit"),
    ({"_scale": 10 ** 400, "fern": [[1, 2]]}, r"_scale: must be a number in \(0, 1024\]"),
    # L3: x == width / y == height lie outside (pixels are 0 <= x < width)
    ({"objects": {"mug": {"image_size": [10, 10], "frames": {"IMG_7": {"positive": [[10, 2]]}}}}},
     r"frame 'IMG_7': positive click \[10.0, 2.0\] lies outside image_size \[10, 10\]"),
    ({"objects": {"mug": {"image_size": [10, 10], "frames": {"IMG_7": {"negative": [[2, 10]], "positive": [[1, 1]]}}}}},
     r"frame 'IMG_7': negative click \[2.0, 10.0\] lies outside image_size"),
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


def test_a_folder_a_fifo_a_huge_file_deep_nesting_and_duplicate_keys_are_named(tmp_path):
    """Issue 44 L4 (a folder or a FIFO read as "does not exist"), L5 (no size cap: a 55 MB
    file took 37 s on every plan), M2 (deep nesting: RecursionError), L2 (a repeated key
    silently kept the last)."""
    import os

    with pytest.raises(InputError, match="is a folder; masks.points_file names the JSON file itself"):
        read_clicks(tmp_path)
    os.mkfifo(tmp_path / "fifo.json")
    with pytest.raises(InputError, match="is not a regular file"):
        read_clicks(tmp_path / "fifo.json")
    big = tmp_path / "big.json"
    with open(big, "wb") as f:
        f.truncate(17 << 20)
    with pytest.raises(InputError, match=r"big.json is 17.0 MiB, more than the 16 MiB"):
        read_clicks(big)
    deep = _write(tmp_path, '{"fern": ' + "[" * 100_000 + "]" * 100_000 + "}", "deep.json")
    with pytest.raises(InputError, match="deep.json: not a click file .JSON nested too deep"):
        read_clicks(deep)
    dup = _write(tmp_path, '{"objects": {"mug": {"frames": {"a": {"positive": [[1, 1]]}}}, '
                           '"mug": {"frames": {"b": {"positive": [[2, 2]]}}}}}', "dup.json")
    with pytest.raises(InputError, match=r"dup.json: key 'mug' appears twice"):
        read_clicks(dup)
    dup2 = _write(tmp_path, '{"fern": [[1, 2]], "fern": [[3, 4]]}', "dup2.json")
    with pytest.raises(InputError, match=r"key 'fern' appears twice"):
        read_clicks(dup2)


def test_frames_are_matched_naming_held_out_extensions_and_misspellings(tmp_path):
    """Issue 44 M3 / click-route messages: the frame checks the masks task and the early
    check share (cobgs.masks.clicks.match_frames)."""
    from cobgs.masks.clicks import match_frames

    views = [("IMG_0001", "IMG_0001.JPG"), ("IMG_0002", "IMG_0002.JPG"), ("IMG_0003", "IMG_0003.JPG")]
    held = [("IMG_0004", "IMG_0004.JPG")]

    def frames(*names):
        data = {"objects": {"mug": {"frames": {n: {"positive": [[1, 1]]} for n in names}}}}
        f = read_clicks(_write(tmp_path, data, "m.json"))
        return f, f.lookup(["mug"])

    assert match_frames(*frames("IMG_0003", "IMG_0001"), views, held) == [2, 0]
    for names, msg in ((("IMG_0004",), r"frame 'IMG_0004': a held-out view"),
                       (("IMG_0001.JPG",), r"frame 'IMG_0001.JPG': frames are named without the file extension: "
                                           r"'IMG_0001'"),
                       (("IMG_0004.JPG",), r"frame 'IMG_0004.JPG': a held-out view"),
                       (("IMG_0010",), r"frame 'IMG_0010': no training view of that name; did you mean .*'IMG_0001'"),
                       (("garbage",), r"frame 'garbage': no training view of that name \(training views like")):
        with pytest.raises(InputError, match=r"m\.json, object 'mug', " + msg):
            match_frames(*frames(*names), views, held)
    # a held-out view named by its image stem (the views are named otherwise)
    named = [("image000", "IMG_4026.JPG")]
    with pytest.raises(InputError, match="frame 'IMG_4027': a held-out view"):
        match_frames(*frames("IMG_4027"), named, [("image001", "IMG_4027.JPG")])


def test_clicks_of_another_aspect_are_refused_not_stretched(tmp_path):
    """Issue 44 H3: a portrait image_size for a landscape view was scaled axis by axis."""
    from cobgs.masks.clicks import check_frame_size

    f = read_clicks(_write(tmp_path, {"objects": {"mug": {"image_size": [3024, 4032],
                                                          "frames": {"IMG_1": {"positive": [[10, 10]]}}}}}))
    entry = f.lookup(["mug"])
    with pytest.raises(InputError, match=r"clicks.json, object 'mug', frame 'IMG_1': the clicks are in a 3024x4032 "
                                         r"frame, but the view's image v.jpg is 1008x756: another aspect ratio"):
        check_frame_size(f, entry, "IMG_1", entry.image_size, (1008, 756), "v.jpg")
    check_frame_size(f, entry, "IMG_1", entry.image_size, (756, 1008), "v.jpg")  # same aspect: scaled
    check_frame_size(f, entry, "IMG_1", None, (1008, 756), "v.jpg")


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
