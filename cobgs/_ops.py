"""Native rasterizer ops (interim: the C++ kernels are being written; until they land,
the native path computes with the PyTorch reference so callers can code against the
final API)."""

from __future__ import annotations

from .reference import rasterize_reference


def rasterize_native(*args):
    return rasterize_reference(*args)
