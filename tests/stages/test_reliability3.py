"""Reliability, round 3 (issue 38): nothing of the user's deleted, no silently ruined
result, a cache that trusts nothing it reads. One test (or a parametrised group) per item."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from stages.commands.cli import main


# -- H1: `cobgs synth --overwrite` replaces only a scene it wrote ------------------------------
def test_h1_synth_overwrite_refuses_a_folder_it_did_not_write(tmp_path, capsys):
    out = tmp_path / "out"
    (out / "sub").mkdir(parents=True)
    (out / "sub" / "thesis.tex").write_text("years of work")
    (out / "notes.txt").write_text("notes")
    rc = main(["synth", "--out", str(out), "--size", "16x16", "--views", "2", "--overwrite"])
    assert rc != 0
    assert "refusing to delete it" in capsys.readouterr().err
    assert (out / "sub" / "thesis.tex").read_text() == "years of work" and (out / "notes.txt").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no temp folder left beside it
    # a plain file at --out is not replaced either
    f = tmp_path / "file.png"
    f.write_bytes(b"\x89PNG")
    assert main(["synth", "--out", str(f), "--size", "16x16", "--views", "2", "--overwrite"]) != 0
    assert f.read_bytes() == b"\x89PNG"
    # a scene synth wrote is replaced as a whole
    scene = tmp_path / "scene"
    assert main(["synth", "--out", str(scene), "--size", "16x16", "--views", "2"]) == 0
    (scene / "stray.txt").write_text("x")
    assert main(["synth", "--out", str(scene), "--size", "16x16", "--views", "3", "--overwrite"]) == 0
    assert not (scene / "stray.txt").exists()
    assert json.loads((scene / "scene.json").read_text())["num_views"] == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file.png", "out", "scene"]


def test_h1_synth_noise_overwrite_refuses_a_folder_it_did_not_write(tmp_path, capsys):
    scene = tmp_path / "scene"
    assert main(["synth", "--out", str(scene), "--size", "16x16", "--views", "2"]) == 0
    dst = tmp_path / "mine"
    dst.mkdir()
    (dst / "keep.txt").write_text("mine")
    rc = main(["synth-noise", str(scene / "masks"), "--out", str(dst), "--overwrite"])
    assert rc != 0 and (dst / "keep.txt").read_text() == "mine"
    assert "refusing to delete it" in capsys.readouterr().err
    noisy = tmp_path / "noisy"
    assert main(["synth-noise", str(scene / "masks"), "--out", str(noisy)]) == 0
    assert main(["synth-noise", str(scene / "masks"), "--out", str(noisy), "--overwrite"]) == 0
    assert (noisy / "noise.json").is_file()


# -- H2 / M1 / L7 / L10: every numeric param has a valid range, checked when planned ----------
DEMO = Path(__file__).resolve().parents[2] / "workflows" / "demo.toml"


@pytest.mark.parametrize("setting", [
    # H2: values that ruined results silently
    "train.prune_min_opacity=inf", "train.ssim_weight=nan", "train.position_lr_init=nan", "train.adam_eps=0",
    "train.init_opacity=1.5", "refine.cobgs.mask_lambda=nan", "refine.cobgs.split_size_fraction=nan",
    "refine.cobgs.raem_footprint_px=-1",
    # M1: errors that came late, after upstream tasks ran
    "train.position_lr_init=-1", "train.adam_eps=nan", "train.log_interval_its=0", "train.backend=evil",
    "evaluate.boundary_ratio=nan", "dataset.workers=-3", "dataset.num_views=-1", "refine.cobgs.label_name=x",
    # L7: no upper bounds
    "train.iterations=10000000000000000000", "refine.cobgs.split_children=1000000", "dataset.width_px=100000",
    # L10
    "evaluate.boundary_ratio=5", "summary.target_miou=nan", "evaluate.warn_psnr_drop_db=inf",
])
def test_params_out_of_range_refused_when_planned_naming_set_and_key(setting):
    from pipeline import Plan, WorkflowError, load_workflow
    from stages.registry import load_registry

    key = setting.split("=")[0]
    with pytest.raises(WorkflowError) as err:
        Plan(load_workflow(DEMO, load_registry(), [setting]))
    text = str(err.value)
    assert "--set" in text and key.split(".")[-1] in text, text
    assert ("must be in" in text or "must be one of" in text or "finite" in text
            or "an integer" in text), text


def test_every_numeric_param_states_a_range_or_is_finite():
    """The rule behind the list above: each float param of every stage has a stated range
    or must be finite; the generated docs list every range."""
    import dataclasses
    import typing

    from cobgs.configs import check_params
    from stages.registry import load_registry

    for stage in load_registry().stages.values():
        cls = stage.params
        if cls is None:
            continue
        todo = [cls]
        while todo:
            c = todo.pop()
            hints = typing.get_type_hints(c)
            for f in dataclasses.fields(c):
                tp = hints[f.name]
                if dataclasses.is_dataclass(tp):
                    todo.append(tp)
            # a float field holding nan is refused by every params class
            for f in dataclasses.fields(c):
                if hints[f.name] is float:
                    inst = c()
                    with pytest.raises(ValueError):
                        check_params(dataclasses.replace(inst, **{f.name: float("nan")}))


# -- M2: a mask of another aspect is refused, not stretched ------------------------------------
def test_m2_mask_of_another_aspect_refused(tmp_path):
    import cv2
    import numpy as np

    from cobgs.data.images import same_aspect
    from stages.masks import _folder_masks

    class V:
        def __init__(self, name, w, h):
            self.name, self.width, self.height = name, w, h

    folder = tmp_path / "m"
    folder.mkdir()
    cv2.imwrite(str(folder / "a.png"), np.full((160, 120), 255, np.uint8))  # 120x160: transposed
    cv2.imwrite(str(folder / "b.png"), np.full((240, 320), 255, np.uint8))  # 320x240: 2x, same aspect
    from stages._common import StageInputError

    with pytest.raises(StageInputError, match=r"a\.png: 120x160 px, but view 'a' is 160x120: another aspect"):
        _folder_masks([V("a", 160, 120)], folder, 0)
    out, info = _folder_masks([V("b", 160, 120)], folder, 0)
    assert out["b"].shape == (120, 160) and info["resized_nearest"] == ["b"]
    assert same_aspect(4032, 3024, 1008, 756) and same_aspect(510, 382, 512, 384)
    assert not same_aspect(120, 160, 160, 120)


# -- M4: a symlink loop (or a link to "/") in a data folder does not hang the fingerprint ----
@pytest.mark.parametrize("target", [".", "..", "/"])
def test_m4_fingerprint_guards_symlink_loops_and_bounds_the_walk(tmp_path, target):
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


def test_m4_status_returns_on_a_data_folder_with_a_loop(tmp_path):
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


# -- L1: a name too long for a file name is refused at load ---------------------------------------
def test_l1_long_value_names_refused_at_load(tmp_path):
    from pipeline import WorkflowError, load_workflow
    from stages.registry import load_registry

    name = "o" * 300
    wf = tmp_path / "w.toml"
    wf.write_text(f'[workflow]\nnested = {{ object = "scene" }}\n[axes.scene.s]\nkind = "synthetic"\n'
                  f'[axes.method.cobgs]\n[axes.object.s.{name}]\n')
    with pytest.raises(WorkflowError, match=r"is 300 bytes long; at most 100"):
        load_workflow(wf, load_registry())


# -- M8 / L2: a bad trained folder is refused when the workflow loads, naming the file ------------
@pytest.mark.parametrize("make, match", [
    (lambda d: None, r"not a 3DGS output folder"),
    (lambda d: _ply(d / "point_cloud" / "iteration_7" / "point_cloud.ply", "int"), r"must be float .*'x \(int\)'"),
    (lambda d: (_ply(d / "point_cloud" / "iteration_7" / "point_cloud.ply"),
                (d / "cfg_args").write_text("Namespace(sh_degree=abc, source_path='x')")), r"cfg_args.*sh_degree"),
    (lambda d: (_ply(d / "point_cloud" / "iteration_7" / "point_cloud.ply"),
                (d / "cameras.json").write_text('[{"img_name": "a", "position": [0, 0, 0], "fx": 1, '
                                                '"width": 1e400}]')), r"cameras\.json.*width"),
])
def test_m8_bad_trained_folder_refused_at_load(tmp_path, make, match):
    from pipeline import WorkflowError, load_workflow
    from stages.registry import load_registry

    d = tmp_path / "out3dgs"
    d.mkdir()
    make(d)
    wf = tmp_path / "w.toml"
    wf.write_text(f'[workflow]\nnested = {{ object = "scene" }}\n[axes.scene.s]\nkind = "synthetic"\n'
                  f'trained = "{d}"\n[axes.method.cobgs]\n[axes.object.s.ball]\n')
    with pytest.raises(WorkflowError, match=match):
        load_workflow(wf, load_registry())


def _ply(path, xyz_type="float"):
    path.parent.mkdir(parents=True, exist_ok=True)
    props = [("x", xyz_type), ("y", xyz_type), ("z", xyz_type)] + [
        (n, "float") for n in ("f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
                               "rot_0", "rot_1", "rot_2", "rot_3")]
    head = "ply\nformat binary_little_endian 1.0\nelement vertex 0\n" + "".join(
        f"property {t} {n}\n" for n, t in props) + "end_header\n"
    path.write_bytes(head.encode())


# -- L3: a decompression-bomb-sized mask names the file --------------------------------------------
def test_l3_huge_mask_png_named(tmp_path):
    import zlib

    from stages._common import StageInputError
    from stages.masks import _folder_masks

    class V:
        name, width, height = "a", 20000, 20000

    # a valid 20000x20000 1-bit PNG written by hand (tiny on disk, 400 Mpx decoded)
    def chunk(tag, data):
        import struct

        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    import struct

    raw = zlib.compress(b"".join(b"\x00" + b"\x00" * 2500 for _ in range(20000)), 9)
    png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 20000, 20000, 1, 0, 0, 0, 0))
           + chunk(b"IDAT", raw) + chunk(b"IEND", b""))
    folder = tmp_path / "m"
    folder.mkdir()
    (folder / "a.png").write_bytes(png)
    with pytest.raises(StageInputError, match=r"mask file .*a\.png: cannot read it as an image .*decompression bomb"):
        _folder_masks([V()], folder, 0)


# -- L5: unreadable workflow files get one clear error ---------------------------------------------
@pytest.mark.parametrize("data, match", [
    (b'[workflow]\nname = "caf\xe9"\n', r"not UTF-8 text: byte 0xe9 on line 2"),
    (b"x = " + b"[" * 100_000 + b"]" * 100_000 + b"\n", r"nested too deep"),
])
def test_l5_unreadable_workflow_files(tmp_path, data, match):
    from pipeline import WorkflowError, load_workflow
    from stages.registry import load_registry

    wf = tmp_path / "w.toml"
    wf.write_bytes(data)
    with pytest.raises(WorkflowError, match=match):
        load_workflow(wf, load_registry())


def test_l5_a_byte_order_mark_is_read(tmp_path):
    from pipeline import load_workflow
    from stages.registry import load_registry

    wf = tmp_path / "w.toml"
    wf.write_bytes(b"\xef\xbb\xbf" + DEMO.read_bytes())
    assert load_workflow(wf, load_registry()).name == "demo"


def test_docs_list_every_param_with_its_range_as_generated():
    """docs/pipeline.md states the valid range of every param, generated from the params
    classes (`cobgs stages --docs docs/pipeline.md` rewrites it), never written twice."""
    from pipeline.commands import DOCS_BEGIN, DOCS_END, stages_toml
    from stages.registry import load_registry

    doc = (Path(__file__).resolve().parents[2] / "docs" / "pipeline.md").read_text()
    inside = doc.split(DOCS_BEGIN, 1)[1].split(DOCS_END, 1)[0]
    expected = f"\n```toml\n{stages_toml(load_registry()).rstrip()}\n```\n"
    assert inside == expected, "docs/pipeline.md is stale: run `cobgs stages --docs docs/pipeline.md`"
    assert "prune_min_opacity = 0.005  # in [0, 1)" in inside and "boundary_ratio = 0.02  # in (0, 0.5]" in inside
