"""External data in cache keys: the fingerprint walk (symlink loops, bounds) and the memo that keys bytes, not file times (issue 38)."""

from __future__ import annotations

import json

import pytest


@pytest.mark.parametrize("target", [".", "..", "/"])
def test_fingerprint_guards_symlink_loops_and_bounds_the_walk(tmp_path, target):
    import os
    import time

    from pipeline.hashing import stat_fingerprint

    d = tmp_path / "masks"
    (d / "obj").mkdir(parents=True)
    (d / "obj" / "0000.png").write_bytes(b"x")
    os.symlink(target, d / "obj" / "link")
    t0 = time.perf_counter()
    with pytest.warns(RuntimeWarning, match=r"fingerprint of .*masks: .*obj/link"):
        a = stat_fingerprint(d, max_files=20_000)
    assert time.perf_counter() - t0 < 30
    assert a == stat_fingerprint(d, max_files=20_000)  # repeatable
    (d / "obj" / "0001.png").write_bytes(b"y")  # still sees the data
    assert stat_fingerprint(d, max_files=20_000) != a

def test_fingerprint_memo_keys_bytes_not_file_times(tmp_path):
    """The cache's fingerprint memo: the same bytes under new times keep the key, through
    a linked folder too; an edit inside the linked folder changes it; the old bytes back
    find the first key; a read-only memo writes nothing and, with nothing recorded, is the
    plain stat fingerprint; a walk cut short (a link loop) is never content-hashed."""
    import os

    from pipeline.hashing import FingerprintMemo, content_fingerprint, stat_fingerprint

    data, shared = tmp_path / "data", tmp_path / "shared"
    data.mkdir()
    shared.mkdir()
    (data / "a.png").write_bytes(b"aaaa")
    (shared / "b.png").write_bytes(b"bbbb")
    os.symlink(shared, data / "linked")

    def retime(delta: int) -> None:
        for f in (data / "a.png", shared / "b.png"):
            st = f.stat()
            os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns + delta))

    ro = FingerprintMemo(tmp_path / "memo", writable=False)
    assert ro.key(data) == stat_fingerprint(data) and not (tmp_path / "memo").exists()
    memo = FingerprintMemo(tmp_path / "memo", writable=True)
    k0 = memo.key(data)
    assert k0 == stat_fingerprint(data) and len(list((tmp_path / "memo").iterdir())) == 1
    retime(3_000_000_000)
    assert stat_fingerprint(data) != k0
    assert memo.key(data) == k0 and ro.key(data) == k0
    c0 = content_fingerprint(data)
    (shared / "b.png").write_bytes(b"bbbc")  # same size, another byte, behind the link
    assert content_fingerprint(data) != c0
    k1 = memo.key(data)
    assert k1 not in (k0,) and k1 == stat_fingerprint(data)
    snapshot = sorted((f.name, f.read_bytes()) for f in (tmp_path / "memo").iterdir())
    (shared / "b.png").write_bytes(b"bbbb")
    retime(5_000_000_000)
    assert ro.key(data) == k0  # read-only: hashes to look up, records nothing
    assert sorted((f.name, f.read_bytes()) for f in (tmp_path / "memo").iterdir()) == snapshot
    assert memo.key(data) == k0
    os.symlink(".", data / "loop")  # a walk that skips a link: stat only, no content read
    with pytest.warns(RuntimeWarning, match="loop"):
        assert memo.key(data) == stat_fingerprint(data)

def test_fingerprint_memo_drops_its_oldest_and_survives_a_damaged_file(tmp_path):
    """The memo keeps the newest KEEP contents per path (the file keeps their age order), and
    a damaged memo file (not str -> str maps) reads as nothing recorded, then is rewritten."""
    import json
    import os

    from pipeline.hashing import FingerprintMemo, stat_fingerprint

    data = tmp_path / "data"
    data.mkdir()
    memo = FingerprintMemo(tmp_path / "memo", writable=True)
    memo.KEEP = 2
    keys = []
    for i, payload in enumerate((b"one", b"two", b"six")):  # same size, new bytes and times
        (data / "a.png").write_bytes(payload)
        os.utime(data / "a.png", ns=(10**18 + i * 10**9, 10**18 + i * 10**9))
        keys.append(memo.key(data))
    (f,) = (tmp_path / "memo").iterdir()
    rec = json.loads(f.read_text())
    assert list(rec["by_content"].values()) == keys[1:]  # the oldest content left, in order
    (data / "a.png").write_bytes(b"one")
    os.utime(data / "a.png", ns=(10**18 + 9 * 10**9, 10**18 + 9 * 10**9))
    assert memo.key(data) == stat_fingerprint(data) != keys[0]  # forgotten: a recompute, never a wrong hit
    f.write_text(json.dumps({"path": rec["path"], "by_stat": {stat_fingerprint(data): {"not": "a str"}},
                                "by_content": {}}))
    assert FingerprintMemo(tmp_path / "memo", writable=False).key(data) == stat_fingerprint(data)
    assert memo.key(data) == stat_fingerprint(data)
    assert all(isinstance(v, str) for v in json.loads(f.read_text())["by_stat"].values())

def test_status_returns_on_a_data_folder_with_a_loop(tmp_path):
    import os
    import subprocess
    import sys

    cap = tmp_path / "capture"
    (cap / "images").mkdir(parents=True)
    (cap / "images" / "0000.png").write_bytes(b"x")
    os.symlink("..", cap / "images" / "up")
    os.symlink(".", cap / "images" / "again")  # two loops: the unguarded walk grows as 2^depth
    wf = tmp_path / "w.toml"
    wf.write_text(f'[workflow]\nnested = {{ object = "scene" }}\n[axes.scene.s]\nkind = "images"\n'
                  f'path = "{cap}"\n[axes.method.cobgs]\n[axes.object.s.ball]\n')
    r = subprocess.run([sys.executable, "-m", "stages.commands.cli", "status", str(wf), "--cache-dir",
                        str(tmp_path / "cache")], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "fingerprint of" in r.stderr and "images/up" in r.stderr, r.stderr[-2000:]
