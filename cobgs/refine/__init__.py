"""Segmentation: COB-GS and the peers on a trained scene.

* :mod:`~cobgs.refine.alternation`: COB-GS (``refine``, ``refine_objects``, ``Refiner``):
  the mask / texture alternation, RAEM; :mod:`~cobgs.refine.scores` (labels, N+/N- scores),
  :mod:`~cobgs.refine.split` (boundary-adaptive splitting), :mod:`~cobgs.refine.consistency`
  (the object-render check);
* :mod:`~cobgs.refine.methods`: every method behind one protocol (``REGISTRY``,
  ``run_method``); :mod:`~cobgs.refine.peers`: no-split, SA3D-GS, FlashSplat;
  :mod:`~cobgs.refine.ngs`: NG-GS's boundary stage;
* :mod:`~cobgs.refine.result`, :mod:`~cobgs.refine.segment`: results, extraction, renders.

Import names from their module; the package itself re-exports nothing.
"""
