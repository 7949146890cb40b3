"""The Gaussians themselves, below everything that renders, trains or segments them.

* :mod:`~cobgs.gaussians.model`: ``GaussianModel`` (tensors, structural edits keeping
  optimizer state aligned, extras such as COB-GS's label logits);
* :mod:`~cobgs.gaussians.ply`: the standard 3DGS PLY layout, read and written;
* :mod:`~cobgs.gaussians.sh`: spherical-harmonic colours (the PyTorch evaluation).

Import names from their module; the package itself re-exports nothing.
"""
