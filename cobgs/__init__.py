"""cobgs: COB-GS segmentation of 3D Gaussian Splatting scenes, CPU first.

Importing the package is cheap and never compiles anything; the native rasterizer is
built on first use of :func:`cobgs.rasterize` (or ahead of time with ``cobgs build``).
"""

from __future__ import annotations

__version__ = "0.1.0"

from cobgs.errors import BuildError, CobgsError, DataError, InputError, ModelError  # noqa: F401


#: The main entry points, importable from ``cobgs`` itself (lazily: ``import cobgs`` stays light).
_PUBLIC = {
    "rasterize": "cobgs.render.rasterize", "RasterOutput": "cobgs.render.rasterize",
    "GaussianModel": "cobgs.train.gaussians", "load_ply": "cobgs.train.ply", "save_ply": "cobgs.train.ply",
    "TrainConfig": "cobgs.configs", "RefineConfig": "cobgs.configs",
    "refine_objects": "cobgs.refine.alternation", "run_method": "cobgs.refine.peers",
    "read_scene": "cobgs.data.readers",
}
# (``cobgs.train`` and ``cobgs.refine`` are the subpackages: their functions are
# ``from cobgs.train import train`` and ``from cobgs.refine import refine``.)


def __getattr__(name):
    # (importlib, not `from . import x`: that looks the name up on this package first and
    # would re-enter __getattr__.)
    if name not in _PUBLIC:
        raise AttributeError(f"module 'cobgs' has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(_PUBLIC[name]), name)
    globals()[name] = value
    return value
