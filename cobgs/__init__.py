"""cobgs: COB-GS segmentation of 3D Gaussian Splatting scenes, CPU first.

Importing the package is cheap and never compiles anything; the native rasterizer is
built on first use of :func:`cobgs.rasterize` (or ahead of time with ``cobgs build``).
"""

from __future__ import annotations

__version__ = "0.1.0"

from .errors import BuildError, CobgsError, DataError, InputError, ModelError  # noqa: F401


def __getattr__(name):  # lazy entry points keep `import cobgs` light
    if name in ("rasterize", "RasterOutput"):
        # importlib, not `from . import rasterize`: the latter looks the name up on this
        # package first and would re-enter __getattr__ forever. Importing the submodule
        # binds `cobgs.rasterize` to the module; rebind it to the function.
        import importlib

        module = importlib.import_module(".rasterize", __name__)
        globals().update(rasterize=module.rasterize, RasterOutput=module.RasterOutput)
        return globals()[name]
    raise AttributeError(f"module 'cobgs' has no attribute {name!r}")
