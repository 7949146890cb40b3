"""tests/benchmarks/bm_rows.py's --versus table (the closing tables of partial bench runs)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest


def _bm_rows():
    path = Path(__file__).resolve().parent / "benchmarks" / "bm_rows.py"
    spec = importlib.util.spec_from_file_location("bm_rows", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _entry(biou: float, occl: float) -> dict:
    views = {f"v{i}": i * 0.01 for i in range(3)}  # per-view values around the mean
    return {"row": {"biou": biou, "biou_occlusion": occl},
            "details": {"per_view": {v: {"biou": biou + d - 0.01} for v, d in views.items()},
                        "per_view_occlusion": {v: {"biou": occl + d - 0.01} for v, d in views.items()}}}


def test_versus_table_names_the_best_peer_by_headline_and_pairs_on_the_same_objects():
    bm = _bm_rows()
    R = {}
    for obj, shift in (("a", 0.0), ("b", 0.1)):
        R[("s", "ref", obj)] = _entry(0.80 + shift, 0.70 + shift)
        R[("s", "base", obj)] = _entry(0.75 + shift, 0.72 + shift)
        R[("s", "p1", obj)] = _entry(0.60 + shift, 0.90 + shift)  # best occlusion-aware, worse headline
        R[("s", "p2", obj)] = _entry(0.70 + shift, 0.50 + shift)
    R[("t", "ref", "c")] = _entry(0.9, 0.9)  # no other row on t: its cells stay empty
    md = bm.versus_tables(R, ["s", "t", "u"], "ref", ["base"], ["p1", "p2"])
    lines = md.splitlines()
    head = lines.index("| scene | ref | base | best peer |")
    s_head, t_head = lines[head + 2], lines[head + 3]
    assert s_head == "| s (2) | 85.00 | 80.00, +5.00 [+5.00, +5.00] | p2: 75.00, +10.00 [+10.00, +10.00] |"
    assert t_head == "| t (1) | 90.00 |  |  |"
    assert not any(line.startswith("| u ") for line in lines)  # a scene without the reference is left out
    # the best peer is chosen on the headline protocol and kept on the other one
    occl = lines[lines.index("| scene | ref | base | best peer |", head + 1) + 2]
    assert occl == "| s (2) | 75.00 | 77.00, -2.00 [-2.00, -2.00] | p2: 55.00, +20.00 [+20.00, +20.00] |"
    assert bm.pair_diff(R, ("s", "ref"), ("s", "p1"), "biou")["diff"] == pytest.approx(20.0)
