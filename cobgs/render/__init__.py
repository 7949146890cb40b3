"""Rendering: the rasterizer and everything that draws Gaussians.

* :mod:`~cobgs.render.rasterize`: ``rasterize`` (the public entry, also ``cobgs.rasterize``);
* :mod:`~cobgs.render.reference`: the pure-PyTorch oracle of every formula and cut-off;
* :mod:`~cobgs.render.ops`: the native ops' wrappers (autograd, fake kernels), and
  :mod:`~cobgs.render.build` / :mod:`~cobgs.render.toolchain`: their build and its checks;
* :mod:`~cobgs.render.camera`, :mod:`~cobgs.gaussians.sh`: cameras and SH colours;
* :mod:`~cobgs.render.image`: a model rendered at a camera; :mod:`~cobgs.render.turntable`:
  orbit GIFs; :mod:`~cobgs.render.splat_pack`: the report viewer's packed Gaussians;
* :mod:`~cobgs.render.selfcheck`: parity and timing checks (``cobgs doctor``).

Import names from their module (``from cobgs.render.camera import Camera``); the package
itself re-exports nothing.
"""
