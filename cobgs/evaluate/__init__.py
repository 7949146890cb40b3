"""Evaluation: :mod:`~cobgs.evaluate.metrics` (IoU, accuracy, boundary IoU, PSNR, SSIM) and
:mod:`~cobgs.evaluate.protocols` (the exact, NVOS and LERF-mask protocols, aggregation).

Import names from their module; the package itself re-exports nothing.
"""
