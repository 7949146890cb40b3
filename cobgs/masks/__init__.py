"""Mask generation through ONNX exports of SAM2 and Grounding DINO."""
