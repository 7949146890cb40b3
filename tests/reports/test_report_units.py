"""Builder pieces without a cache or a browser: tables, best values, formatting, quoted
paper numbers, method options and the picture composition."""

from __future__ import annotations

import math

import numpy as np
import pytest

from reports import fmt, paper
from reports.pictures import FN_RGB, FP_RGB, crop_window, overlay, slug
from reports.methods import options_of
from reports.tables import Column, best_indices, build_table


# -- best values -------------------------------------------------------------------------
def test_best_indices_max_min_and_ties():
    assert best_indices([0.5, 0.9, 0.7], "max") == {1}
    assert best_indices([0.5, 0.9, 0.7], "min") == {0}
    assert best_indices([0.9, 0.5, 0.9], "max") == {0, 2}


def test_best_indices_ignores_missing_and_never_marks_a_lone_or_uniform_value():
    assert best_indices([None, float("nan"), 0.3, "n/a"], "max") == set()  # one measured value
    assert best_indices([0.4, 0.4, 0.4], "max") == set()  # nothing singled out
    assert best_indices([None, 0.2, float("nan"), 0.1], "max") == {1}


def _cells(table, key):
    i = [c.key for c in table.columns].index(key)
    return [row.cells[i] for row in table.rows]


def test_table_marks_best_per_group_and_skips_incomplete_rows_and_quoted_columns():
    cols = [Column("scene", "Scene", numeric=False), Column("iou", "mIoU", fmt.pct, better="max"),
            Column("t", "Time", fmt.seconds, better="min"), Column("paper", "paper", quoted=True, better="max")]
    recs = [
        {"scene": "a", "iou": 0.80, "t": 2.0, "paper": 0.99},
        {"scene": "a", "iou": 0.90, "t": 3.0, "paper": 0.10},
        {"scene": "a", "iou": 0.95, "t": 1.0, "_nobest": True},  # incomplete: never best
        {"scene": "b", "iou": 0.50, "t": 4.0},
        {"scene": "b", "iou": 0.70, "t": 5.0},
    ]
    t = build_table("t", "caption", cols, recs, group_by="scene")
    best_iou = ["best" in c.classes for c in _cells(t, "iou")]
    assert best_iou == [False, True, False, False, True]
    assert ["best" in c.classes for c in _cells(t, "t")] == [True, False, False, True, False]
    assert not any("best" in c.classes for c in _cells(t, "paper"))
    assert all("quoted" in c.classes for c in _cells(t, "paper"))


def test_table_cells_sort_by_raw_value_and_leave_missing_empty():
    t = build_table("t", "c", [Column("iou", "mIoU", fmt.pct)], [{"iou": 0.123456}, {"iou": None},
                                                                 {"iou": float("nan")}])
    cells = _cells(t, "iou")
    assert cells[0].text == "12.35" and cells[0].sort == pytest.approx(0.123456)
    assert [c.text for c in cells[1:]] == ["", ""] and [c.sort for c in cells[1:]] == ["", ""]


def test_column_rejects_an_unknown_direction():
    with pytest.raises(ValueError, match="better"):
        Column("x", "X", better="higher")


# -- formatting --------------------------------------------------------------------------
@pytest.mark.parametrize("fn", [fmt.pct, fmt.db, fmt.count, fmt.seconds, fmt.nbytes, fmt.timestamp])
def test_formatters_never_invent_a_number(fn):
    for missing in (None, float("nan"), float("inf"), "x", True):
        assert fn(missing) == ""


def test_formatters():
    assert fmt.pct(0.92134) == "92.13" and fmt.quoted_pct(92.1) == "92.1"
    assert fmt.db(0.04, signed=True) == "+0.04" and fmt.db(-1.234) == "-1.23"
    assert fmt.count(12345) == "12\u2009345"
    assert fmt.seconds(0.25) == "250 ms" and fmt.seconds(8.44) == "8.4 s" and fmt.seconds(125) == "2 min 05 s"
    assert fmt.nbytes(2.5 * 1024 ** 3) == "2.5 GiB" and fmt.nbytes(512) == "512 B"


# -- quoted paper numbers ----------------------------------------------------------------
DEFAULT_COBGS = {"delta": None, "bags": True, "bgtr": True, "raem": "released", "score": "count",
                 "stage_length_views": 2.0, "seed": 0}


def _params(**cobgs):
    return {"method": "cobgs", "cobgs": {**DEFAULT_COBGS, **cobgs}}


def test_paper_method_identifies_cobgs_and_its_table5_rows():
    assert paper.paper_method("cobgs", _params()) == ("cobgs", (True, True, True))
    assert paper.paper_method("cobgs", _params(bgtr=False)) == ("cobgs", (True, False, True))
    assert paper.paper_method("cobgs", _params(raem="off", bgtr=False)) == ("cobgs", (True, False, False))
    assert paper.paper_method("cobgs", _params(raem="paper")) == ("cobgs", (True, True, True))
    # a δ-sweep item or another score is not the paper's method: no quoted number for it
    assert paper.paper_method("cobgs", _params(delta=0.3)) is None
    assert paper.paper_method("cobgs", _params(score="weighted")) is None
    assert paper.paper_method("sa3d", None) == ("sa3d",)


def test_nvos_quotes_match_the_paper_tables():
    q = paper.nvos_quote(paper.paper_method("cobgs", _params()))
    assert q.values == {"iou": 92.1, "acc": 98.6} and "Table 1" in q.source
    assert paper.nvos_quote(("flashsplat",)).values == {"iou": 91.8, "acc": 98.6}
    assert paper.nvos_quote(("sa3d",)).values == {"iou": 90.7, "acc": 98.3}
    assert paper.nvos_quote(("nosplit",)).values == {"iou": 91.2, "acc": 98.3}  # Table 5, row 1
    assert paper.nvos_quote(("cobgs", (True, True, False))).values == {"iou": 91.9, "acc": 98.4}
    assert paper.nvos_quote(("cobgs", (True, False, True))) is None  # not a row of Table 5
    assert paper.nvos_quote(None) is None


def test_psnr_and_lerf_quotes():
    joint = paper.nvos_psnr_quote("trex", ("cobgs", (True, True, True)))
    assert joint.values == {"psnr": 24.97, "psnr_vanilla": 24.68}
    assert paper.nvos_psnr_quote("trex", ("cobgs", (True, False, True))).values["psnr"] == 23.35  # M.O
    assert paper.nvos_psnr_quote("trex", ("flashsplat",)) is None
    assert paper.nvos_psnr_quote("lego", ("cobgs", (True, True, True))) is None
    assert paper.lerf_quote("Teatime", ("cobgs", (True, True, True))).values == {"iou": 77.2, "biou": 72.8}
    assert paper.lerf_quote("teatime", ("sa3d",)) is None


# -- method options ----------------------------------------------------------------------
def test_options_list_only_what_differs_from_the_defaults_in_the_method_section():
    defaults = {"method": "cobgs", "scene_type": "auto", "cobgs": {"bgtr": True, "delta": None},
                "sa3d": {"lr": 1.0}}
    got = {"method": "cobgs", "scene_type": "auto", "cobgs": {"bgtr": False, "delta": 0.3}, "sa3d": {"lr": 2.0}}
    assert options_of("cobgs", got, defaults) == ["bgtr=false", "delta=0.3"]
    assert options_of("sa3d", {**got, "method": "sa3d"}, defaults) == ["lr=2.0"]
    assert options_of("cobgs", defaults, defaults) == []


# -- pictures ----------------------------------------------------------------------------
def test_overlay_paints_false_positives_and_negatives_apart():
    img = np.full((6, 6, 3), 100, np.uint8)
    gt = np.zeros((6, 6), bool)
    gt[1:4, 1:4] = True
    pred = np.zeros((6, 6), bool)
    pred[2:5, 2:5] = True
    out = overlay(img, gt, pred).astype(int)
    fp, fn, tp = (4, 4), (1, 1), (2, 2)
    assert np.argmax(out[fp]) == int(np.argmax(FP_RGB)) and np.argmax(out[fn]) == int(np.argmax(FN_RGB))
    assert tuple(out[tp]) == (100, 100, 100)  # true positives keep the image
    assert out[5, 0].max() < 100  # context is dimmed


def test_crop_window_goes_where_errors_are_and_stays_inside():
    gt = np.zeros((60, 90), bool)
    gt[10:50, 10:80] = True
    err = np.zeros_like(gt)
    err[45:50, 70:80] = True
    top, left, size = crop_window(gt, [err])
    assert size == 20 and 0 <= top <= 40 and 0 <= left <= 70
    assert top <= 45 and top + size >= 50 and left <= 70 and left + size >= 80
    # no error at all: the window is centred on the GT outline, both sides in view
    t2, l2, s2 = crop_window(gt, [np.zeros_like(gt)])
    assert 0 <= t2 <= 40 and 0 <= l2 <= 70
    assert 0.2 < gt[t2:t2 + s2, l2:l2 + s2].mean() < 0.8


def test_slug_keeps_names_apart():
    assert slug("ball") == "ball"
    a, b = slug("green apple"), slug("green_apple")
    assert a != b and "/" not in a and " " not in a
    assert not math.isnan(len(slug("../x")))
    assert ".." not in slug("../x").split("-")[0]


def test_thin_errors_survive_the_page_size_overlay(tmp_path):
    """A one-pixel-wide false positive on a GT four times wider than the page picture
    still shows in the overlay, and the counts are the full-resolution ones."""
    from PIL import Image

    from reports.pictures import MAX_WIDTH_PX, MethodPictures, PictureSet, compose

    h, w = 300, 4 * MAX_WIDTH_PX
    gt = np.zeros((h, w), bool)
    gt[100:200, 600:1200] = True
    pred = gt.copy()
    pred[100:200, 1200] = True
    ps = PictureSet("s", "o", "v", methods=[MethodPictures("m", "M")])
    compose(ps, np.full((h // 4, w // 4, 3), 120, np.uint8), gt, {"m": pred}, {}, tmp_path, "x")
    assert (ps.methods[0].fp_px, ps.methods[0].fn_px) == (100, 0)
    ov = np.asarray(Image.open(tmp_path / "m" / "overlay.png")).astype(int)
    assert ov.shape[1] == MAX_WIDTH_PX
    red = np.abs(ov - np.array(FP_RGB)).sum(axis=2) < 60
    assert red[25:50].any() and red.sum() >= 20


def test_plot_labels_are_text_not_tex(tmp_path):
    """A scene or object named with a "$" (or TeX-like text) is drawn as typed; it used to
    raise in matplotlib's math-text parser and fail the whole report."""
    from reports import plots

    name = "cup$_$2/cob$^$gs"  # math text: invalid TeX (ValueError)
    assert plots.time_breakdown(tmp_path / "t.svg", [(name, {"train": 3.0, "refine": 1.0})],
                                ["train", "refine"])
    assert name in (tmp_path / "t.svg").read_text()


def test_log_axis_ticks_are_plain_numbers(tmp_path):
    """With math text off (names are text), the score curves' log axis must not print raw
    math markup such as $\\mathdefault{10^{3}}$ as its tick labels."""
    import numpy as np

    from reports import plots

    scores = np.linspace(0, 1, 5000) ** 3
    assert plots.score_curves(tmp_path / "s.svg", [("scene / obj", [("mask stage 1", scores)], 0.5)])
    svg = (tmp_path / "s.svg").read_text()
    assert "mathdefault" not in svg and "$" not in svg


def test_psnr_plot_stems_start_at_each_methods_own_vanilla(tmp_path):
    """Methods run on different scenes (a δ sweep limited to one scene) have different
    vanilla means: each stem starts at its own (the change printed is psnr - its vanilla),
    no shared dashed line; with one vanilla for all, the line and its label are drawn."""
    from reports import plots

    colors = {"a": "#111111", "b": "#222222"}
    assert plots.psnr(tmp_path / "p.svg", ["a", "b"], [33.01, 23.17], [33.01, 23.00], colors)
    svg = (tmp_path / "p.svg").read_text()
    assert "33.01 (+0.00)" in svg and "23.17 (+0.17)" in svg and "vanilla 2" not in svg
    assert "mean PSNR for that method" in svg
    assert plots.psnr(tmp_path / "q.svg", ["a", "b"], [31.0, 30.5], [30.0, 30.0], colors)
    svg = (tmp_path / "q.svg").read_text()
    assert "vanilla 30.00" in svg and "31.00 (+1.00)" in svg


def test_scene_notes_say_when_training_started_from_a_random_box():
    """Issue 38 M10: the report says when a scene's training started from a random box."""
    from reports.records import _init_note

    assert "random box (100000)" in _init_note({"initial_points": "random box (100000)"})[0]
    assert _init_note({"initial_points": 1234}) == [] and _init_note({}) == []


def test_scene_notes_name_the_training_recipe():
    """Issue 45: the scene table says which recipe trained each scene (a 3dgs train.json leaves
    the field out; a scene trained elsewhere gets no recipe note)."""
    from reports.records import _recipe_note

    assert _recipe_note({"config": {"iterations": 30000}, "iterations": 30000}) == [
        "training recipe: 3dgs (the paper's schedule, 30000 iterations)"]
    fast = {"config": {"recipe": "fast", "iterations": 12000, "resolution_schedule": True,
                       "gaussian_budget_per_pixel": 0.3}, "iterations": 12000}
    assert _recipe_note(fast) == ["training recipe: fast (12000 iterations, resolution schedule, "
                                  "Gaussian budget (0.3 per pixel))"]  # an entry from before the count was written
    fast["config"].update(gaussian_budget_multiplier=36.0, budget_threshold_gate=True)
    fast["gaussian_budget"] = 65340
    assert _recipe_note(fast) == ["training recipe: fast (12000 iterations, resolution schedule, Gaussian budget "
                                  "65,340 (0.3 per pixel or 36.0 x the initial points, the larger) as a ceiling)"]
    assert _recipe_note({"config": {"recipe": "3dgs"}, "imported": {"iteration": 7000}}) == []
    assert _recipe_note({}) == []


def test_markdown_tables_escape_names():
    """Issue 38 L4: names go into tables.md; `a|b` and a newline stay inside one cell."""
    from reports.tables import Cell, Column, Row, Table, to_markdown

    t = Table(id="t", caption="scene a|b", columns=[Column("object", "obj|ect", numeric=False),
                                                     Column("iou", "IoU")],
              rows=[Row([Cell("a|b\nc"), Cell("0.5")])])
    md = to_markdown(t).splitlines()
    header, row = md[2], md[4]
    unescaped = lambda line: len(__import__("re").findall(r"(?<!\\)\|", line))  # noqa: E731
    assert unescaped(header) == unescaped(row) == 3
    assert "a\\|b c" in row and "obj\\|ect" in header
