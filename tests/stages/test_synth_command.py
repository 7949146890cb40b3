"""`cobgs synth` / `cobgs synth-noise --overwrite` replace only a folder they wrote (issue 38)."""

from __future__ import annotations

import json

from stages.commands.cli import main


def test_synth_overwrite_refuses_a_folder_it_did_not_write(tmp_path, capsys):
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

def test_synth_noise_overwrite_refuses_a_folder_it_did_not_write(tmp_path, capsys):
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
