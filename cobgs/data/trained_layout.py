"""The files of a scene trained elsewhere, checked without loading it (standard library only).

A workflow's ``trained`` attribute names an original-3DGS output folder
(``point_cloud/iteration_<N>/point_cloud.ply``, ``cfg_args``, ``cameras.json``, optional
``chkpnt<N>.pth``) or a standard 3DGS PLY. :func:`check_trained` is what the workflow's
load runs: it finds the PLY, reads its header (the standard properties present and float),
and parses ``cfg_args`` and ``cameras.json``, so that a bad folder is named before any
task runs; :mod:`cobgs.data.trained3dgs` then reads the data itself with the same finders.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

from cobgs.errors import DataError

_PLY_TYPES_FLOAT = {"float", "float32", "double", "float64"}
_CORE = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
         "rot_0", "rot_1", "rot_2", "rot_3")


def saved_iterations(folder: Path) -> dict[int, Path]:
    """iteration -> ``point_cloud/iteration_<N>/point_cloud.ply`` of a 3DGS output folder."""
    pc = Path(folder) / "point_cloud"
    found = {}
    if pc.is_dir():
        for d in pc.iterdir():
            m = re.fullmatch(r"iteration_(\d+)", d.name)
            if m and (d / "point_cloud.ply").is_file():
                found[int(m.group(1))] = d / "point_cloud.ply"
    return found


def find_trained_ply(path: Path, iteration: int = 0) -> tuple[Path, int]:
    """(the PLY, its iteration; 0 for a bare PLY) of a trained scene.

    Raises:
        DataError: no such folder / file, not a 3DGS output folder, or no such iteration.
    """
    path = Path(path)
    if path.is_file():
        if iteration:
            raise DataError("an iteration is only meaningful for a 3DGS output folder", path)
        return path, 0
    if not path.is_dir():
        raise DataError("trained scene not found (a 3DGS output folder or a PLY file)", path)
    found = saved_iterations(path)
    if not found:
        raise DataError("not a 3DGS output folder: no point_cloud/iteration_<N>/point_cloud.ply", path)
    if iteration:
        if iteration not in found:
            raise DataError(f"no iteration {iteration} (saved iterations: {sorted(found)})", path / "point_cloud")
        return found[iteration], iteration
    it = max(found)
    return found[it], it


def ply_properties(path: Path) -> dict[str, dict[str, str]]:
    """element -> {property: type} from a PLY file's header (nothing else is read)."""
    out: dict[str, dict[str, str]] = {}
    try:
        with open(path, "rb") as f:
            if f.readline().strip() != b"ply":
                raise DataError("not a PLY file (no 'ply' magic line)", path)
            element = None
            for _ in range(100_000):
                line = f.readline()
                if not line:
                    raise DataError("PLY header without end_header", path)
                words = line.decode("ascii", "replace").split()
                if not words:
                    continue
                if words[0] == "end_header":
                    return out
                if words[0] == "element" and len(words) >= 2:
                    element = words[1]
                    out[element] = {}
                elif words[0] == "property" and element is not None and len(words) >= 3:
                    if words[1] == "list":
                        out[element][words[-1]] = "list"
                    else:
                        out[element][words[2]] = words[1]
    except OSError as exc:
        raise DataError(f"cannot read the PLY: {exc}", path) from exc
    raise DataError("PLY header too long", path)


def check_ply_header(path: Path) -> None:
    """A standard 3DGS vertex layout: every core property present and float."""
    props = ply_properties(path).get("vertex")
    if props is None:
        raise DataError("no 'vertex' element: not a 3DGS PLY", path)
    missing = [p for p in _CORE if p not in props]
    if missing:
        raise DataError(f"missing standard 3DGS properties {missing}", path)
    not_float = [f"{p} ({props[p]})" for p in _CORE if props[p] not in _PLY_TYPES_FLOAT]
    if not_float:
        raise DataError(f"standard 3DGS properties must be float (float32 / float64), got {not_float}", path)


def read_cfg_args(path: Path) -> dict:
    """The simple values of 3DGS's ``cfg_args`` (``Namespace(key=value, ...)``), read as text;
    ``sh_degree`` must be an integer in 0..3."""
    if not path.is_file():
        return {}
    text = path.read_text(errors="replace")
    out = {}
    for key, val in re.findall(r"(\w+)=('[^']*'|\"[^\"]*\"|[-\w.]+)", text):
        if val[:1] in "'\"":
            out[key] = val[1:-1]
        elif re.fullmatch(r"-?\d+", val):
            out[key] = int(val)
        elif re.fullmatch(r"-?\d*\.\d*(e-?\d+)?", val):
            out[key] = float(val)
        else:
            out[key] = val
    if "sh_degree" in out and not (isinstance(out["sh_degree"], int) and 0 <= out["sh_degree"] <= 3):
        raise DataError(f"sh_degree must be an integer in 0..3, got {out['sh_degree']!r}", path)
    return out


def read_cameras_json(path: Path) -> dict[str, tuple[list[float], float, int]]:
    """name -> (position, fx, width) of 3DGS's ``cameras.json``, every number checked."""
    try:
        cams = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise DataError(f"unreadable cameras.json: {e}", path) from e
    out = {}
    try:
        for c in cams:
            name = Path(str(c["img_name"])).stem
            pos = [float(v) for v in c["position"]]
            fx, width = float(c["fx"]), c["width"]
            if isinstance(width, float) and width.is_integer():
                width = int(width)
            if len(pos) != 3 or not all(math.isfinite(v) for v in pos) or not (math.isfinite(fx) and fx > 0) \
                    or not isinstance(width, int) or not 0 < width <= 1 << 20:
                raise DataError(f"camera {name!r}: expected a finite 3-vector position, fx > 0 and "
                                f"an integer width in 1..{1 << 20}, got position {pos}, fx {fx}, width {width!r}",
                                path)
            out[name] = (pos, fx, width)
    except (TypeError, KeyError, ValueError, OverflowError) as e:
        raise DataError(f"expected a list of {{img_name, position, fx, width, ...}}: {e!r}", path) from e
    return out


def check_trained(path: Path, iteration: int = 0) -> Path:
    """Everything about a trained scene that can be checked without loading it (module
    docstring); returns its PLY.

    Raises:
        DataError: naming the file at fault.
    """
    ply, _ = find_trained_ply(path, iteration)
    check_ply_header(ply)
    if Path(path).is_dir():
        read_cfg_args(Path(path) / "cfg_args")
        if (Path(path) / "cameras.json").is_file():
            read_cameras_json(Path(path) / "cameras.json")
    return ply
