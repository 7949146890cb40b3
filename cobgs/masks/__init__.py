"""Mask generation through ONNX exports of SAM2 (video) and Grounding DINO.

* :mod:`~cobgs.masks.api`: ``generate_masks`` (text, two-stage: paper Alg. 1),
  ``generate_masks_from_scribbles`` (NVOS), ``generate_masks_from_points``,
  ``generate_masks_from_clicks``, ``FramePrompt``;
* :mod:`~cobgs.masks.clicks`: click files (SAGA-v2's NVOS points, the per-object layout);
* :mod:`~cobgs.masks.manifest`: the model folder's manifests (``load_manifest``);
  :mod:`~cobgs.masks.session`: onnxruntime sessions (``SessionOptions``);
* :mod:`~cobgs.masks.two_stage`, :mod:`~cobgs.masks.video`, :mod:`~cobgs.masks.gdino`,
  :mod:`~cobgs.masks.scribbles`: the pieces; :mod:`~cobgs.masks.export`: the ONNX export.

Import names from their module; the package itself re-exports nothing.
"""
