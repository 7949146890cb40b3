"""PLY I/O: standard 3DGS layout, exact round trip, extras, malformed files."""

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from cobgs.errors import DataError
from cobgs.gaussians.model import GaussianModel
from cobgs.gaussians.ply import load_ply, save_ply


def _model(n=30, degree=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2 - 1
    return GaussianModel(
        torch.randn(n, 3, generator=g),
        torch.randn(n, 3, generator=g),
        torch.randn(n, 4, generator=g),
        torch.randn(n, generator=g),
        torch.randn(n, 1, 3, generator=g),
        torch.randn(n, k, 3, generator=g),
        active_sh_degree=min(1, degree),
    )


def test_round_trip_exact_with_extras(tmp_path):
    m = _model()
    m.add_extra("label_logits", torch.randn(30), fill=0.0)
    m.add_extra("object_id", torch.arange(30) * 7 - 3, fill=-1)
    m.add_extra("embedding", torch.randn(30, 5).double(), fill=0.5)
    p = save_ply(tmp_path / "sub" / "scene.ply", m)
    r = load_ply(p)
    assert len(r) == 30 and r.sh_degree == 3 and r.active_sh_degree == 1
    assert r.extras == ["label_logits", "object_id", "embedding"]
    assert r.fill == {"label_logits": 0.0, "object_id": -1, "embedding": 0.5}
    for k in m.data:
        assert r.data[k].dtype == m.data[k].dtype, k
        assert torch.equal(r.data[k], m.data[k]), k
    assert not list((tmp_path / "sub").glob("*.tmp"))  # atomic write left no temp file


def test_standard_layout_for_viewers(tmp_path):
    m = _model(4)
    save_ply(tmp_path / "a.ply", m)
    ply = PlyData.read(str(tmp_path / "a.ply"))
    assert [e.name for e in ply.elements] == ["vertex"]
    assert ply.byte_order == "<" and not ply.text
    names = list(ply["vertex"].data.dtype.names)
    expect = (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(45)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )
    assert names == expect
    v = ply["vertex"].data
    assert all(v.dtype[n] == np.dtype("<f4") for n in names)
    # f_rest is channel-major: f_rest_{c * 15 + j} = shN[:, j, c].
    shN = m.shN.detach().numpy()
    for c in range(3):
        for j in range(15):
            np.testing.assert_array_equal(v[f"f_rest_{c * 15 + j}"], shN[:, j, c])
    np.testing.assert_array_equal(v["opacity"], m.opacity_logits.detach().numpy())  # logit
    np.testing.assert_array_equal(v["scale_1"], m.log_scales.detach().numpy()[:, 1])  # log
    np.testing.assert_array_equal(v["rot_0"], m.quats.detach().numpy()[:, 0])  # w first


def test_lower_degree_and_foreign_file_without_normals(tmp_path):
    m = _model(6, degree=1)
    save_ply(tmp_path / "d1.ply", m, extras=())
    r = load_ply(tmp_path / "d1.ply")
    assert r.sh_degree == 1 and torch.equal(r.shN, m.shN)
    # A file written by another tool: no normals, no cobgs comments, degree 0.
    names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    arr = np.zeros(3, dtype=[(n, "f4") for n in names])
    arr["x"] = [1, 2, 3]
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(tmp_path / "foreign.ply"))
    f = load_ply(tmp_path / "foreign.ply")
    assert f.sh_degree == 0 and f.active_sh_degree == 0 and torch.equal(f.means[:, 0], torch.tensor([1.0, 2, 3]))


def test_malformed_files_raise_data_error(tmp_path):
    with pytest.raises(DataError, match="not found"):
        load_ply(tmp_path / "missing.ply")
    (tmp_path / "junk.ply").write_bytes(b"this is not a ply file\n")
    with pytest.raises(DataError, match="junk.ply"):
        load_ply(tmp_path / "junk.ply")
    save_ply(tmp_path / "ok.ply", _model(50))
    data = (tmp_path / "ok.ply").read_bytes()
    (tmp_path / "trunc.ply").write_bytes(data[: len(data) - 1000])
    with pytest.raises(DataError, match="trunc.ply"):
        load_ply(tmp_path / "trunc.ply")
    arr = np.zeros(2, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(tmp_path / "points.ply"))
    with pytest.raises(DataError, match="missing standard 3DGS properties"):
        load_ply(tmp_path / "points.ply")
    PlyData([PlyElement.describe(arr, "point")]).write(str(tmp_path / "noverts.ply"))
    with pytest.raises(DataError, match="vertex"):
        load_ply(tmp_path / "noverts.ply")


def _standard_vertex(n, extra=(), rest=0):
    names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", *[f"f_rest_{i}" for i in range(rest)],
             "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    arr = np.zeros(n, dtype=[(nm, "f4") for nm in names] + list(extra))
    arr["rot_0"] = 1.0
    return arr


def test_foreign_formats_are_named_with_what_to_do(tmp_path):
    # antimatter15's .splat: 32 bytes per Gaussian, no header
    (tmp_path / "scene.splat").write_bytes(np.zeros(4 * 32, np.uint8).tobytes())
    with pytest.raises(DataError, match=r"\.splat file .*convert it to a standard 3DGS PLY") as info:
        load_ply(tmp_path / "scene.splat")
    assert "scene.splat" in str(info.value)
    # PlayCanvas / SuperSplat compressed PLY: a chunk element and packed_* properties
    chunk = np.zeros(1, dtype=[("min_x", "f4"), ("max_x", "f4")])
    packed = np.zeros(3, dtype=[("packed_position", "u4"), ("packed_rotation", "u4"),
                                ("packed_scale", "u4"), ("packed_color", "u4")])
    PlyData([PlyElement.describe(chunk, "chunk"), PlyElement.describe(packed, "vertex")]).write(
        str(tmp_path / "compressed.ply"))
    with pytest.raises(DataError, match="compressed PLY .*decompress it first") as info:
        load_ply(tmp_path / "compressed.ply")
    assert "compressed.ply" in str(info.value)


def test_gap_in_f_rest_numbering_is_reported_as_such(tmp_path):
    arr = _standard_vertex(2, rest=9)
    names = [n if n != "f_rest_4" else "f_rest_40" for n in arr.dtype.names]
    arr.dtype.names = names
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(tmp_path / "gap.ply"))
    with pytest.raises(DataError, match="gap: f_rest_4 is missing") as info:
        load_ply(tmp_path / "gap.ply")
    assert "gap.ply" in str(info.value)


def test_unrelated_properties_are_ignored(tmp_path):
    arr = _standard_vertex(3, extra=[("red", "u1"), ("filter_3D", "f4"), ("feat_1", "f4"),
                                     ("feat_3", "f4"), ("semantic_0", "f4"), ("semantic_1", "f4")])
    arr["semantic_1"] = [1, 2, 3]
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(tmp_path / "tool.ply"))
    m = load_ply(tmp_path / "tool.ply")
    assert len(m) == 3 and torch.equal(m.data["semantic"][:, 1], torch.tensor([1.0, 2, 3]))
    assert "feat" not in m.extras  # feat_1, feat_3: not numbered 0..k-1, ignored


def test_non_finite_values_are_refused_with_a_count(tmp_path):
    arr = _standard_vertex(5)
    arr["x"][1] = np.nan
    arr["opacity"][3] = np.inf
    arr["scale_0"][3] = np.nan
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(tmp_path / "nan.ply"))
    with pytest.raises(DataError, match=r"2 of 5 Gaussians have non-finite values .*'x'.*'opacity'") as info:
        load_ply(tmp_path / "nan.ply")
    assert "nan.ply" in str(info.value)


@pytest.mark.parametrize("props, dtype", [(("x", "y", "z"), "i4"), (("opacity",), "u1")])
def test_integer_core_properties_are_refused_naming_them(tmp_path, props, dtype):
    """Issue 38 M3: x/y/z as int32 or opacity as uchar imported as other numbers."""
    arr = _standard_vertex(4)
    descr = [(n, dtype if n in props else arr.dtype[n].str) for n in arr.dtype.names]
    out = np.zeros(4, dtype=descr)
    for n in arr.dtype.names:
        out[n] = arr[n].astype(out.dtype[n]) if n not in props else np.arange(4)
    PlyData([PlyElement.describe(out, "vertex")]).write(str(tmp_path / "int.ply"))
    with pytest.raises(DataError, match=rf"must be float .*'{props[0]} \(") as info:
        load_ply(tmp_path / "int.ply")
    assert "int.ply" in str(info.value)
