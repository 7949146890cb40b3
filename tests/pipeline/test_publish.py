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


def test_earlier_reports_and_exports_without_the_new_fields_need_replace(tmp_path):
    """Issue 56 H3: folders written before the marker carried generator / files list folders,
    not files, so a user's file inside them cannot be told from ours. Recognised by the exact
    shape their writer gave the marker, they are replaced only with ``replace``; before, a
    forged ``{"format": "cobgs-report", "workflow": "x"}`` made everything under data/ img/ ...
    count as ours, and an old export's ``{"file": "demo"}`` covered a thesis.tex below demo/."""
    rep = tmp_path / "rep"
    (rep / "data").mkdir(parents=True)
    (rep / "data" / "mydataset.bin").write_text("precious")
    (rep / "report.json").write_text(json.dumps({"format": "cobgs-report", "workflow": "x"}))
    before = _tree(rep)
    with pytest.raises(DestinationError, match=r"a report of an older cobgs, whose report.json does not list its "
                                               r"files.*--replace"):
        publish_folder(rep, _writer({"index.html": "new"}), "report.json", "report")
    assert _tree(rep) == before
    publish_folder(rep, _writer({"index.html": "new"}), "report.json", "report", replace=True)
    assert _tree(rep).keys() == {"index.html", "report.json"}

    exp = tmp_path / "exp"
    (exp / "demo" / "m" / "o").mkdir(parents=True)
    (exp / "demo" / "thesis.tex").write_text("three years")
    (exp / "summary.csv").write_text("a")
    legacy = {"workflow": "/w.toml", "cache_dir": "/c", "missing": [],
              "copied": [{"file": "summary.csv"}, {"file": "demo"}]}
    (exp / "export.json").write_text(json.dumps(legacy))
    before = _tree(exp)
    with pytest.raises(DestinationError, match="an export of an older cobgs"):
        publish_folder(exp, _writer({"summary.csv": "b"}), "export.json", "export")
    assert _tree(exp) == before
    check_destination(exp, "export.json", "export", replace=True)  # the user's explicit choice
    legacy["extra"] = 1  # not the shape the old writer gave it: never ours
    (exp / "export.json").write_text(json.dumps(legacy))
    with pytest.raises(DestinationError, match="export.json was not written by `cobgs export`"):
        check_destination(exp, "export.json", "export", replace=True)


def test_what_appears_while_the_folder_is_built_is_kept(tmp_path):
    """Issue 56 H4: the destination was checked once, before minutes of work, and swapped
    without a second look; a thesis.tex created meanwhile was lost."""
    dest = tmp_path / "t"

    def slow_writer(tmp: Path) -> None:
        dest.mkdir()  # the user, while the report is built
        (dest / "thesis.tex").write_text("mine")
        _writer({"index.html": "new"})(tmp)

    with pytest.raises(DestinationError, match="non-empty folder that this tool did not write"):
        publish_folder(dest, slow_writer, "report.json", "report")
    assert _tree(dest) == {"thesis.tex": "mine"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t"]  # no temporary folder, no lock file

    # a file added to an earlier report of ours between the last check and the exchange: the
    # previous folder is looked at once more after the exchange, and swapped back
    import pipeline.publish as pub

    ours = tmp_path / "ours"
    publish_folder(ours, _writer({"index.html": "one"}), "report.json", "report")
    real = pub.check_destination
    calls = []

    def late_check(d, *a, **k):
        real(d, *a, **k)
        calls.append(d)
        if len(calls) == 3:  # the last check before the exchange passed; then the user writes
            (ours / "late.txt").write_text("written at the last moment")

    pub.check_destination = late_check
    try:
        with pytest.raises(DestinationError, match=r"appeared in it while the report was built: \['late.txt'\]"):
            publish_folder(ours, _writer({"index.html": "two"}), "report.json", "report")
    finally:
        pub.check_destination = real
    assert (ours / "late.txt").is_file() and (ours / "index.html").read_text() == "one"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ours", "t"]


def test_one_publisher_at_a_time_and_the_other_gets_one_line(tmp_path):
    """Issue 56 H4 / M2: a concurrent export into the folder a report is building reported
    success and was then replaced; two publishers racing into an absent folder left the
    loser with ``[Errno 39] Directory not empty``. The lock beside the destination refuses
    the second at once, naming the holder; the first finishes."""
    import subprocess
    import sys
    import textwrap

    dest = tmp_path / "m"
    started = tmp_path / "started"
    code = textwrap.dedent(f"""
        import json, sys, time
        from pathlib import Path
        from pipeline.publish import publish_folder
        def write(tmp):
            Path({str(started)!r}).write_text("x")
            time.sleep(4)
            (tmp / "report.json").write_text(json.dumps({{"workflow": "w"}}))
        publish_folder(Path({str(dest)!r}), write, "report.json", "report")
    """)
    from pipeline_testutil import REPO

    proc = subprocess.Popen([sys.executable, "-c", code], cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)})
    try:
        import time

        t0 = time.time()
        while not started.exists() and time.time() - t0 < 60:
            time.sleep(0.05)
        with pytest.raises(DestinationError, match=rf"{dest} is being written by another cobgs process \(.*pid "
                                                   rf"{proc.pid}"):
            publish_folder(dest, _writer({"index.html": "export"}), "export.json", "export")
    finally:
        assert proc.wait(timeout=120) == 0
    assert json.loads((dest / "report.json").read_text())["generator"] == "cobgs report"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m", "started"]


def test_a_full_disk_is_one_line_and_the_destination_is_kept(tmp_path):
    """Issue 56 M3: ``[Errno 28]`` reached the user as a traceback."""
    import errno

    dest = tmp_path / "r"
    publish_folder(dest, _writer({"index.html": "one"}), "report.json", "report")

    def full(tmp: Path) -> None:
        (tmp / "index.html").write_text("partial")
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp / "img" / "x.png"))

    with pytest.raises(DestinationError, match=r"no space left on the device while writing the report.*left as it "
                                               r"was"):
        publish_folder(dest, full, "report.json", "report")
    assert (dest / "index.html").read_text() == "one" and sorted(p.name for p in tmp_path.iterdir()) == ["r"]


def test_a_mount_point_is_swapped_inside_and_a_kill_is_undone(tmp_path, monkeypatch):
    """Issue 56 M1: a destination that is a mount point (a Docker volume, a USB root) cannot
    be renamed (``[Errno 16] Device or resource busy``): its content is swapped entry by
    entry inside it, and a swap a kill interrupted is undone by the next publish."""
    import pipeline.publish as pub

    vol = tmp_path / "vol"
    vol.mkdir()
    monkeypatch.setattr(pub, "is_mount_point", lambda p: os.path.abspath(p) == str(vol))
    real_rename = os.rename

    def no_rename_of_the_mount(a, b, *args, **kw):
        if os.path.abspath(a) == str(vol) or os.path.abspath(b) == str(vol):
            raise OSError(16, "Device or resource busy")
        return real_rename(a, b, *args, **kw)

    monkeypatch.setattr(os, "rename", no_rename_of_the_mount)
    monkeypatch.setattr(pub, "exchange_paths", lambda a, b: (_ for _ in ()).throw(OSError(16, "busy")))
    publish_folder(vol, _writer({"index.html": "one", "img/a.png": "a"}), "report.json", "report")
    assert _tree(vol).keys() == {"index.html", "img/a.png", "report.json"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["vol"]
    publish_folder(vol, _writer({"index.html": "two"}), "report.json", "report")
    assert _tree(vol).keys() == {"index.html", "report.json"} and (vol / "index.html").read_text() == "two"
    (vol / "thesis.tex").write_text("mine")
    with pytest.raises(DestinationError, match=r"\['thesis.tex'\]"):
        publish_folder(vol, _writer({"index.html": "three"}), "report.json", "report")
    assert (vol / "thesis.tex").read_text() == "mine" and (vol / "index.html").read_text() == "two"
    (vol / "thesis.tex").unlink()

    # a kill in the middle of the swap: the journal and the two halves are left inside
    dead = 2 ** 22 + 1
    work = vol / f".cobgs-report.swap-{dead}"
    (work / "new").mkdir(parents=True)
    (work / "old").mkdir()
    (work / "new" / "report.json").write_text('{"new": 1}')
    real_rename(vol / "report.json", work / "old" / "report.json")  # the marker left first
    real_rename(vol / "index.html", work / "old" / "index.html")
    (vol / "plots").mkdir()  # one new entry had come in
    (work / "journal.json").write_text(json.dumps({"marker": "report.json", "out": ["index.html", "report.json"],
                                                   "in": ["plots", "report.json"], "new_marker": '{"new": 1}'}))
    publish_folder(vol, _writer({"index.html": "four"}), "report.json", "report")
    assert _tree(vol).keys() == {"index.html", "report.json"} and (vol / "index.html").read_text() == "four"
    assert not any(p.name.startswith(".cobgs") for p in vol.iterdir())


def test_a_real_bind_mount_is_detected(tmp_path):
    """:func:`is_mount_point` sees a bind mount from the same filesystem (a Docker volume),
    which os.path.ismount misses; then a publish into it works. Needs the right to mount
    (root, as in CI); elsewhere only the simulated mount point above runs."""
    import subprocess

    from pipeline.publish import is_mount_point

    src, vol = tmp_path / "src", tmp_path / "vol"
    src.mkdir()
    vol.mkdir()
    if subprocess.run(["mount", "--bind", str(src), str(vol)], capture_output=True).returncode != 0:
        pytest.skip("no right to mount here (not root): the simulated mount point test covers the swap")
    try:
        assert is_mount_point(vol) and not is_mount_point(src)
        publish_folder(vol, _writer({"index.html": "one"}), "report.json", "report")
        publish_folder(vol, _writer({"index.html": "two"}), "report.json", "report")
        assert _tree(src) == {"index.html": "two", "report.json": (src / "report.json").read_text()}
    finally:
        subprocess.run(["umount", str(vol)], check=True)


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
