"""The Gaussians and their optimisation.

* :mod:`~cobgs.gaussians.model`: ``GaussianModel``; :mod:`~cobgs.gaussians.ply`: its PLY I/O;
* :mod:`~cobgs.train.optimize`: the 3DGS training loop (``train``, ``Trainer``) and its recipes;
* :mod:`~cobgs.train.losses`: L1 + SSIM; :mod:`~cobgs.train.adam_moments`: the Adam state
  COB-GS's texture stages continue; :mod:`~cobgs.train.visible_adam`: selective Adam.

Import names from their module; the package itself re-exports nothing.
"""
