"""A scene trained elsewhere (the scene's `trained` attribute): bad folders are refused when the workflow loads (issue 38)."""

from __future__ import annotations

import json

import pytest


def _ply(path, xyz_type="float"):
    path.parent.mkdir(parents=True, exist_ok=True)
    props = [("x", xyz_type), ("y", xyz_type), ("z", xyz_type)] + [
        (n, "float") for n in ("f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
                               "rot_0", "rot_1", "rot_2", "rot_3")]
    head = "ply\nformat binary_little_endian 1.0\nelement vertex 0\n" + "".join(
        f"property {t} {n}\n" for n, t in props) + "end_header\n"
    path.write_bytes(head.encode())


@pytest.mark.parametrize("make, match", [
    (lambda d: None, r"not a 3DGS output folder"),
    (lambda d: _ply(d / "point_cloud" / "iteration_7" / "point_cloud.ply", "int"), r"must be float .*'x \(int\)'"),
    (lambda d: (_ply(d / "point_cloud" / "iteration_7" / "point_cloud.ply"),
                (d / "cfg_args").write_text("Namespace(sh_degree=abc, source_path='x')")), r"cfg_args.*sh_degree"),
    (lambda d: (_ply(d / "point_cloud" / "iteration_7" / "point_cloud.ply"),
                (d / "cameras.json").write_text('[{"img_name": "a", "position": [0, 0, 0], "fx": 1, '
                                                '"width": 1e400}]')), r"cameras\.json.*width"),
])
def test_bad_trained_folder_refused_at_load(tmp_path, make, match):
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
