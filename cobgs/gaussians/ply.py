"""PLY I/O in the standard 3DGS layout, plus optional extra per-Gaussian properties.

One binary little-endian element named ``vertex`` with float32 properties, in the order
the original 3DGS writes them (so common splat viewers open the files):

    x y z  nx ny nz  f_dc_0..2  f_rest_0..(3(K-1)-1)  opacity  scale_0..2  rot_0..3

``opacity`` is the logit, ``scale_*`` the log scales, ``rot_*`` the (w, x, y, z)
quaternion; ``f_rest`` is channel-major (all red coefficients 1..K-1, then green, then
blue), the transpose of the model's [N, K-1, 3]. Extras follow: an [N] extra ``foo`` is
the property ``foo``, an [N, k] extra is ``foo_0..foo_{k-1}``; float32/float64 keep their
type, integers are stored as int32 (range-checked) and read back as int64, uint8 stays
uint8. Header comments record each extra's fill value and the active SH degree, so a
round trip reproduces the model exactly.
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from cobgs._atomic import write_atomic
from cobgs.errors import DataError, InputError
from cobgs.gaussians.model import GaussianModel, check_extra_name

log = logging.getLogger(__name__)

_SH_REST_COUNTS = {0: 0, 9: 1, 24: 2, 45: 3}
_COMMENT_EXTRA = "cobgs_extra"
_COMMENT_DEGREE = "cobgs_active_sh_degree"


def _standard_names(n_rest: int) -> list[str]:
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(n_rest)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


def save_ply(path: os.PathLike | str, model: GaussianModel, extras: Optional[Sequence[str]] = None) -> Path:
    """Write ``model`` atomically (temporary file + rename).

    Args:
        path: destination ``.ply``.
        model: the Gaussians.
        extras: extra attributes to include (default: all of the model's extras; ``()``
            writes a pure standard 3DGS file).

    Returns:
        the path written.
    """
    from plyfile import PlyData, PlyElement

    path = Path(path)
    names = model.extras if extras is None else list(extras)
    for name in names:
        if name not in model.extras:
            raise InputError(f"model has no extra {name!r} (extras: {model.extras})")
    n = len(model)
    d = {k: v.detach().cpu() for k, v in model.data.items()}
    # [N, 3 (K-1)], channel-major; explicit width so that an empty model (an empty
    # segmentation) still writes a valid, empty PLY.
    shN = d["shN"].transpose(1, 2).reshape(n, 3 * d["shN"].shape[1])
    cols: list[tuple[str, str, np.ndarray]] = []
    std = torch.cat(
        [
            d["means"],
            torch.zeros(n, 3),
            d["sh0"].reshape(n, 3),
            shN,
            d["opacity_logits"][:, None],
            d["log_scales"],
            d["quats"],
        ],
        1,
    ).float().numpy()
    for i, name in enumerate(_standard_names(shN.shape[1])):
        cols.append((name, "f4", std[:, i]))
    comments = [f"{_COMMENT_DEGREE} {model.active_sh_degree}"]
    for name in names:
        t = d[name]
        arr, ply_type = _extra_to_numpy(name, t)
        flat = arr.reshape(n, int(np.prod(arr.shape[1:], dtype=np.int64)))
        if t.dim() == 1:
            cols.append((name, ply_type, flat[:, 0]))
        else:
            if t.dim() != 2:
                raise InputError(f"extra {name!r} must be [N] or [N, k] to be saved, got {list(t.shape)}")
            cols += [(f"{name}_{j}", ply_type, flat[:, j]) for j in range(flat.shape[1])]
        comments.append(f"{_COMMENT_EXTRA} {name} {model.fill.get(name, 0)!r}")
    vertex = np.empty(n, dtype=[(c, t) for c, t, _ in cols])
    for c, _, v in cols:
        vertex[c] = v
    el = PlyElement.describe(vertex, "vertex")
    return write_atomic(path, lambda f: PlyData([el], text=False, byte_order="<", comments=comments).write(f))


def _extra_to_numpy(name: str, t: torch.Tensor) -> tuple[np.ndarray, str]:
    if t.dtype == torch.float32:
        return t.numpy(), "f4"
    if t.dtype == torch.float64:
        return t.numpy(), "f8"
    if t.dtype == torch.uint8:
        return t.numpy(), "u1"
    if t.dtype in (torch.int8, torch.int16, torch.int32, torch.int64):
        if t.numel() and (int(t.min()) < -(2**31) or int(t.max()) >= 2**31):
            raise InputError(f"extra {name!r} has values outside the int32 range PLY can store")
        return t.to(torch.int32).numpy(), "i4"
    raise InputError(f"extra {name!r} has dtype {t.dtype}; PLY supports float32/64, int, uint8")


def load_ply(path: os.PathLike | str, device: str | torch.device = "cpu") -> GaussianModel:
    """Read a 3DGS PLY (ours or any tool's that writes the standard layout).

    Every property outside the standard layout becomes an extra (``foo_0..foo_{k-1}``
    group into one [N, k] extra); properties that cannot be (oddly numbered, names or types
    of another tool's) are ignored and logged. Normals are optional.

    Raises:
        DataError: missing file, not a PLY (a ``.splat`` file or a compressed PLY is named
            as such, with what to convert it to), truncated data, no ``vertex`` element, a
            missing standard property, a gap in the ``f_rest_*`` numbering, or Gaussians
            with non-finite values (counted); the message names the file.
    """
    from plyfile import PlyData

    path = Path(path)
    if not path.is_file():
        raise DataError("PLY file not found", path)
    with open(path, "rb") as fh:
        magic = fh.read(4)
    if magic[:3] != b"ply":
        if path.suffix.lower() == ".splat" or (path.stat().st_size % 32 == 0 and magic != b""):
            raise DataError("this is a .splat file (antimatter15's 32-byte-per-Gaussian format: "
                            "position, scale, 8-bit colour and rotation; no SH, quantised "
                            "opacity), not a PLY; convert it to a standard 3DGS PLY first "
                            "(SuperSplat, for one, opens .splat and exports .ply)", path)
        raise DataError(f"not a PLY file (it starts with {magic!r}, a PLY with b'ply')", path)
    try:
        ply = PlyData.read(os.fspath(path))
    except Exception as e:  # plyfile raises several types (PlyParseError, ValueError, ...)
        raise DataError(f"malformed or truncated PLY: {e}", path) from e
    elements = [el.name for el in ply.elements]
    if "vertex" not in elements:
        raise DataError(f"no 'vertex' element (elements: {elements})", path)
    v = ply["vertex"].data
    props = list(v.dtype.names or ())
    if "chunk" in elements or any(p.startswith("packed_") for p in props):
        raise DataError("this is a compressed PLY (PlayCanvas / SuperSplat's packed layout: a "
                        "'chunk' element and packed_position / packed_rotation / packed_scale / "
                        "packed_color), not the standard 3DGS layout; decompress it first "
                        "(SuperSplat exports the uncompressed .ply)", path)
    n = len(v)
    numbered = {int(p[7:]): p for p in props if re.fullmatch(r"f_rest_\d+", p)}
    if numbered and sorted(numbered) != list(range(len(numbered))):
        gaps = sorted(set(range(max(numbered) + 1)) - set(numbered))
        raise DataError(f"the f_rest_* numbering has a gap: f_rest_{gaps[0]} is missing "
                        f"({len(numbered)} of f_rest_0..f_rest_{max(numbered)} present)", path)
    rest = [numbered[i] for i in range(len(numbered))]
    if len(rest) not in _SH_REST_COUNTS:
        raise DataError(
            f"expected f_rest_0..f_rest_k with 3(K-1) in {{0, 9, 24, 45}} properties, got {len(rest)}",
            path,
        )
    need = [p for p in _standard_names(len(rest)) if p not in ("nx", "ny", "nz")]
    missing = [p for p in need if p not in props]
    if missing:
        raise DataError(f"missing standard 3DGS properties {missing}", path)
    not_float = [f"{p} ({v.dtype[p]})" for p in need if v.dtype[p].kind != "f"]
    if not_float:
        raise DataError(f"standard 3DGS properties must be float (float32 / float64), got {not_float}: "
                        "positions, scales, rotations, opacities and colours stored as integers would "
                        "be read as other numbers (a quantised or compressed export? decompress it first)", path)
    bad = np.zeros(n, bool)
    bad_props = []
    for p in need:
        nf = ~np.isfinite(np.asarray(v[p], dtype=np.float64))
        if nf.any():
            bad |= nf
            bad_props.append(p)
    if bad.any():
        raise DataError(f"{int(bad.sum())} of {n} Gaussians have non-finite values (NaN or inf) "
                        f"in {bad_props}", path)

    def col(name):
        return torch.from_numpy(np.ascontiguousarray(v[name], dtype=np.float32))

    def stack(names):
        return torch.stack([col(c) for c in names], 1) if names else torch.zeros(n, 0)

    means = stack(["x", "y", "z"])
    sh0 = stack(["f_dc_0", "f_dc_1", "f_dc_2"])[:, None, :]
    k1 = len(rest) // 3
    shN = stack(rest).reshape(n, 3, k1).transpose(1, 2).contiguous()
    opac = col("opacity")
    log_scales = stack(["scale_0", "scale_1", "scale_2"])
    quats = stack(["rot_0", "rot_1", "rot_2", "rot_3"])

    active, fills = None, {}
    for c in ply.comments:
        parts = c.split()
        if len(parts) == 2 and parts[0] == _COMMENT_DEGREE:
            active = int(parts[1])
        elif len(parts) == 3 and parts[0] == _COMMENT_EXTRA:
            fills[parts[1]] = _parse_number(parts[2])
    sh_degree = _SH_REST_COUNTS[len(rest)]
    if active is not None and not 0 <= active <= sh_degree:
        raise DataError(f"active SH degree {active} in the header exceeds the data's degree {sh_degree}", path)
    model = GaussianModel(means, log_scales, quats, opac, sh0, shN, active_sh_degree=active)

    standard = set(_standard_names(len(rest)))
    groups, odd = _group_extras([p for p in props if p not in standard])
    ignored = list(odd)
    for name, cols in groups:
        arrays = [np.asarray(v[c]) for c in cols]
        stacked = arrays[0] if cols == [name] else np.stack(arrays, 1)
        try:
            check_extra_name(name)
            t = torch.from_numpy(np.ascontiguousarray(stacked))
        except (InputError, TypeError):  # a name or type another tool uses: not ours
            ignored.extend(cols)
            continue
        if t.dtype in (torch.int8, torch.int16, torch.int32):
            t = t.to(torch.int64)
        model.add_extra(name, t, fill=fills.get(name, 0))
    if ignored:
        log.info("%s: ignored properties that are neither standard 3DGS nor readable extras: %s",
                 path, ignored)
    return model.to(device) if str(device) != "cpu" else model


def _group_extras(props: list[str]) -> tuple[list[tuple[str, list[str]]], list[str]]:
    """Group ``foo_0..foo_{k-1}`` into one vector extra, in order of first appearance.
    Returns (the groups, the properties that look numbered but are not 0..k-1: not ours,
    ignored by the caller)."""
    order: list[str] = []
    groups: dict[str, dict[int, str]] = {}
    for p in props:
        m = re.match(r"^(.*)_(\d+)$", p)
        base = m.group(1) if m else p
        if base not in groups:
            order.append(base)
            groups[base] = {}
        groups[base][int(m.group(2)) if m else -1] = p
    out, odd = [], []
    for base in order:
        idx = groups[base]
        if list(idx) == [-1]:
            out.append((base, [base]))
        elif sorted(idx) == list(range(len(idx))):
            out.append((base, [idx[i] for i in range(len(idx))]))
        else:
            odd.extend(sorted(idx.values()))
    return out, odd


def _parse_number(s: str):
    try:
        return int(s)
    except ValueError:
        return float(s)
