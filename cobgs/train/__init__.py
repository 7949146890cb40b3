"""3DGS training: the optimisation of the Gaussians (the model and its PLY I/O live below, in
:mod:`cobgs.gaussians`).

* :mod:`~cobgs.train.optimize`: the 3DGS training loop (``train``, ``Trainer``) and its recipes;
* :mod:`~cobgs.train.losses`: L1 + SSIM; :mod:`~cobgs.train.adam_moments`: the Adam state
  COB-GS's texture stages continue; :mod:`~cobgs.train.visible_adam`: selective Adam.

Import names from their module; the package itself re-exports nothing.
"""
