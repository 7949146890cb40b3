"""cobgs: COB-GS segmentation of 3D Gaussian Splatting scenes, CPU first.

Importing the package is cheap and never compiles anything; the native rasterizer is
built on first use of :func:`cobgs.rasterize` (or ahead of time with ``cobgs build``).

OpenMP: the rasterizer's parallel loops run on the OpenMP runtime torch loads, whose threads
by default spin after every loop, burning the cores other work needs; on a busy machine that
made renders 2-4x slower. Importing cobgs therefore sets ``OMP_WAIT_POLICY=PASSIVE`` (idle
threads sleep) when the variable is unset and torch is not imported yet: the runtime reads it
once, when torch loads it. Import cobgs before torch (or set the variable yourself) to get it;
``tests/benchmarks/bm_omp_wait.py`` measures both ways.
"""

from __future__ import annotations

import os as _os
import sys as _sys

if "OMP_WAIT_POLICY" not in _os.environ and "torch" not in _sys.modules:
    _os.environ["OMP_WAIT_POLICY"] = "PASSIVE"

__version__ = "0.1.0"

from cobgs.errors import BuildError, CobgsError, DataError, InputError, ModelError  # noqa: F401


#: The public names of the library, each with its one home (loaded on first use, PEP 562:
#: ``import cobgs`` stays light and never imports torch). Everything else is imported from its
#: module (``from cobgs.render.camera import Camera``); the subpackages re-export nothing.
_HOME = {
    "rasterize": "cobgs.render.rasterize", "RasterOutput": "cobgs.render.reference",
    "GaussianModel": "cobgs.gaussians.model", "load_ply": "cobgs.gaussians.ply", "save_ply": "cobgs.gaussians.ply",
    "TrainConfig": "cobgs.configs", "RefineConfig": "cobgs.configs", "SA3DConfig": "cobgs.configs",
    "FlashSplatConfig": "cobgs.configs",
    "refine_objects": "cobgs.refine.alternation", "run_method": "cobgs.refine.methods",
    "read_scene": "cobgs.data.readers",
}
__all__ = sorted(_HOME) + ["BuildError", "CobgsError", "DataError", "InputError", "ModelError", "__version__"]
# (``cobgs.train`` and ``cobgs.refine`` are the subpackages: their functions are
# ``from cobgs.train.optimize import train`` and ``from cobgs.refine.alternation import refine``.)


def __getattr__(name):
    # (importlib, not `from . import x`: that looks the name up on this package first and
    # would re-enter __getattr__.)
    if name not in _HOME:
        raise AttributeError(f"module 'cobgs' has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(_HOME[name]), name)
    globals()[name] = value
    return value
