"""Workflow files as users write them: long value names, unreadable files, a byte-order mark (issue 38)."""

from __future__ import annotations

from pathlib import Path

import pytest

DEMO = Path(__file__).resolve().parents[2] / "workflows" / "demo.toml"


def test_long_value_names_refused_at_load(tmp_path):
    from pipeline import WorkflowError, load_workflow
    from stages.registry import load_registry

    name = "o" * 300
    wf = tmp_path / "w.toml"
    wf.write_text(f'[workflow]\nnested = {{ object = "scene" }}\n[axes.scene.s]\nkind = "synthetic"\n'
                  f'[axes.method.cobgs]\n[axes.object.s.{name}]\n')
    with pytest.raises(WorkflowError, match=r"is 300 bytes long; at most 100"):
        load_workflow(wf, load_registry())

@pytest.mark.parametrize("data, match", [
    (b'[workflow]\nname = "caf\xe9"\n', r"not UTF-8 text: byte 0xe9 on line 2"),
    (b"x = " + b"[" * 100_000 + b"]" * 100_000 + b"\n", r"nested too deep"),
])
def test_unreadable_workflow_files(tmp_path, data, match):
    from pipeline import WorkflowError, load_workflow
    from stages.registry import load_registry

    wf = tmp_path / "w.toml"
    wf.write_bytes(data)
    with pytest.raises(WorkflowError, match=match):
        load_workflow(wf, load_registry())

def test_a_byte_order_mark_is_read(tmp_path):
    from pipeline import load_workflow
    from stages.registry import load_registry

    wf = tmp_path / "w.toml"
    wf.write_bytes(b"\xef\xbb\xbf" + DEMO.read_bytes())
    assert load_workflow(wf, load_registry()).name == "demo"
