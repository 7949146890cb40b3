"""Export scripts users run where torch, the model code and the checkpoints are.

``cobgs export-onnx sam2 ...`` and ``cobgs export-onnx gdino ...`` write exactly the
files of the ONNX contract plus ``manifest.json``, and verify the exported graphs against
the PyTorch model on one image before reporting success. Nothing here is imported by the
mask-generation runtime.
"""
