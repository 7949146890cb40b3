"""tests/benchmarks/bm_segmentation.py reads the tables the report writes (issue 58 item 4): the
faithful twin of a checked row and which rows are COB-GS's own come from the report's
ablation.csv (reports.ablation), not from a rule of its own."""

from __future__ import annotations

import csv
import importlib.util
import json
from pathlib import Path


def _bm():
    path = Path(__file__).resolve().parent / "benchmarks" / "bm_segmentation.py"
    spec = importlib.util.spec_from_file_location("bm_segmentation", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _write(path: Path, rows: list[dict]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    keys = list(dict.fromkeys(k for r in rows for k in r))
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)


def test_the_check_table_and_the_peer_targets_read_the_reports_columns(tmp_path):
    base = {"scene": "s", "masks": "exact", "bags": "✓", "bgtr": "✓", "raem": "paper", "stage": ""}
    _write(tmp_path / "data" / "ablation.csv", [
        {**base, "method": "faithful_a", "check": "", "role": "variant", "twin": "", "biou": 0.5},
        {**base, "method": "faithful_b", "check": "", "role": "variant", "twin": "", "biou": 0.6},
        {**base, "method": "ours", "check": "per_use", "role": "reference", "twin": "faithful_b", "biou": 0.7},
        {**base, "method": "ngs", "check": "", "role": "peer", "twin": "", "biou": 0.4, "stage": "NG-GS"}])
    _write(tmp_path / "data" / "differences.csv", [
        {"scene": "s", "masks": "exact", "d:faithful_b": 10.0, "lo:faithful_b": 8.0, "hi:faithful_b": 12.0,
         "d:ngs": -3.0, "lo:ngs": -4.0, "hi:ngs": -2.0}])
    (tmp_path / "report.json").write_text(json.dumps({"reference": "ours"}))
    bm = _bm()
    lines = bm.check_lines(tmp_path)
    row = next(line for line in lines if "| ours |" in line)
    assert "| faithful_b |" in row and "60.00 → 70.00" in row and "+10.00 [+8.00, +12.00]" in row
    target = bm.target_lines(tmp_path)[0]
    assert "1 scene x peer comparisons" in target and "s (exact) vs ngs: -3.00" in target  # NG-GS: a peer
