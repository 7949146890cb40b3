"""pipeline.publish: what a report / export may replace, and what it must refuse.

A destination is replaced only when it is absent, empty, or a folder that ``publish_folder``
wrote (its marker names the generator and the workflow and lists its files). Issue 44 H1:
the marker's mere presence used to be enough, so a user's folder holding a ``report.json``
of their own was deleted whole.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from pipeline.publish import DestinationError, check_destination, publish_folder


def _writer(files: dict[str, str], workflow: str = "/w/demo.toml"):
    def write(tmp: Path) -> None:
        for rel, text in files.items():
            (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
            (tmp / rel).write_text(text)
        (tmp / "report.json").write_text(json.dumps({"workflow": workflow, "counts": 3}))
    return write


def _tree(root: Path) -> dict[str, str]:
    return {p.relative_to(root).as_posix(): p.read_text() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("marker_text", ['{"coverage": 91}', "not json", "[1, 2]",
                                         '{"generator": "cobgs report"}',  # no workflow, no files
                                         '{"generator": "someone else", "workflow": "w", "files": []}',
                                         '{"generator": "cobgs export", "workflow": "w", "files": []}'])
def test_a_marker_cobgs_did_not_write_is_refused_and_nothing_is_deleted(tmp_path, marker_text):
    user = tmp_path / "P"
    (user / "src").mkdir(parents=True)
    (user / "src" / "main.c").write_text("int main;")
    (user / "NOTES.md").write_text("x")
    (user / "report.json").write_text(marker_text)
    before = _tree(user)
    with pytest.raises(DestinationError, match=r"report\.json was not written by `cobgs report`"):
        publish_folder(user, _writer({"index.html": "new"}), "report.json", "report")
    with pytest.raises(DestinationError, match="report.json was not written"):
        publish_folder(user, _writer({"index.html": "new"}), "report.json", "report", replace=True)
    assert _tree(user) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["P"]  # no temporary folder left


def test_a_folder_we_wrote_is_replaced_and_its_marker_names_generator_workflow_files(tmp_path):
    dest = tmp_path / "r"
    publish_folder(dest, _writer({"index.html": "one", "img/a.png": "a"}), "report.json", "report")
    rec = json.loads((dest / "report.json").read_text())
    assert rec["generator"] == "cobgs report" and rec["workflow"] == "/w/demo.toml"
    assert rec["files"] == ["img/a.png", "index.html", "report.json"] and rec["counts"] == 3
    publish_folder(dest, _writer({"index.html": "two"}), "report.json", "report")
    assert _tree(dest).keys() == {"index.html", "report.json"} and (dest / "index.html").read_text() == "two"


def test_files_the_user_added_to_our_folder_are_named_and_kept_unless_replace(tmp_path):
    dest = tmp_path / "r"
    publish_folder(dest, _writer({"index.html": "one", "img/a.png": "a"}), "report.json", "report")
    (dest / "thesis.tex").write_text("my thesis")
    (dest / "img" / "mine.png").write_text("mine")
    (dest / "empty_dir").mkdir()
    before = _tree(dest)
    with pytest.raises(DestinationError) as err:
        publish_folder(dest, _writer({"index.html": "two"}), "report.json", "report")
    msg = str(err.value)
    assert "'empty_dir/'" in msg and "'img/mine.png'" in msg and "'thesis.tex'" in msg and "--replace" in msg
    assert _tree(dest) == before
    publish_folder(dest, _writer({"index.html": "two"}), "report.json", "report", replace=True)
    assert _tree(dest).keys() == {"index.html", "report.json"}


def test_earlier_reports_and_exports_without_the_new_fields_are_still_ours(tmp_path):
    """Folders written before the marker carried generator / files: recognised by the exact
    shape their writer gave the marker (a report's fixed layout, an export's copied list)."""
    rep = tmp_path / "rep"
    (rep / "img").mkdir(parents=True)
    (rep / "img" / "x.png").write_text("x")
    (rep / "index.html").write_text("old")
    (rep / "report.json").write_text(json.dumps({"format": "cobgs-report", "version": 1, "workflow": "/w.toml"}))
    publish_folder(rep, _writer({"index.html": "new"}), "report.json", "report")
    assert (rep / "index.html").read_text() == "new"

    exp = tmp_path / "exp"
    (exp / "s" / "m" / "o" / "pred_masks").mkdir(parents=True)
    (exp / "s" / "m" / "o" / "pred_masks" / "v.png").write_text("m")
    (exp / "summary.csv").write_text("a")
    legacy = {"workflow": "/w.toml", "cache_dir": "/c", "missing": [],
              "copied": [{"file": "summary.csv"}, {"file": "s/m/o/pred_masks"}]}
    (exp / "export.json").write_text(json.dumps(legacy))
    check_destination(exp, "export.json", "export")  # accepted as it is
    (exp / "notes.txt").write_text("mine")
    with pytest.raises(DestinationError, match=r"\['notes.txt'\]"):
        check_destination(exp, "export.json", "export")
    legacy["extra"] = 1  # not the shape the old writer gave it
    (exp / "export.json").write_text(json.dumps(legacy))
    with pytest.raises(DestinationError, match="export.json was not written by `cobgs export`"):
        check_destination(exp, "export.json", "export", replace=True)


def test_a_destination_under_a_file_or_a_link_is_refused_naming_it(tmp_path):
    """Issue 44 M5: ``--to F/sub`` where F is a file was a FileExistsError traceback."""
    f = tmp_path / "F"
    f.write_text("a file")
    with pytest.raises(DestinationError, match=f"lies under {f}, which is a file"):
        publish_folder(f / "sub", _writer({}), "report.json", "report")
    with pytest.raises(DestinationError, match="exists and is not a folder"):
        publish_folder(f, _writer({}), "report.json", "report")
    target = tmp_path / "real"
    publish_folder(target, _writer({"index.html": "x"}), "report.json", "report")
    link = tmp_path / "link"
    os.symlink(target, link)
    with pytest.raises(DestinationError, match="is a symbolic link"):
        publish_folder(link, _writer({}), "report.json", "report")
    assert f.read_text() == "a file" and (target / "index.html").read_text() == "x"


def test_a_writer_without_its_marker_leaves_nothing(tmp_path):
    dest = tmp_path / "d"
    with pytest.raises(RuntimeError, match="did not write report.json"):
        publish_folder(dest, lambda tmp: (tmp / "index.html").write_text("x"), "report.json", "report")
    assert list(tmp_path.iterdir()) == []
