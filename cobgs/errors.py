"""Typed errors raised by the cobgs library.

Every message says what was expected, what arrived and, where there is one, which file
or argument was at fault. Library code raises these instead of using ``assert`` (which
``python -O`` removes).
"""

from __future__ import annotations

import os
from typing import Optional


class CobgsError(Exception):
    """Base class of every error the library raises on purpose."""


class InputError(CobgsError, ValueError):
    """A function argument has the wrong shape, dtype, device or value."""


class DataError(CobgsError):
    """A file or data set on disk is missing, unreadable or inconsistent.

    Args:
        message: what is wrong, in words.
        path: the offending file or folder, included in the message.
    """

    def __init__(self, message: str, path: Optional[os.PathLike | str] = None):
        self.path = None if path is None else os.fspath(path)
        super().__init__(f"{self.path}: {message}" if self.path else message)


class ModelError(DataError):
    """A user-supplied model (ONNX export, manifest) breaks the contract."""


class DivergenceError(CobgsError, RuntimeError):
    """An optimisation produced a non-finite loss or parameter, or lost every Gaussian: the
    result would be garbage, so the run stops (naming the iteration) instead of saving it."""


class BuildError(CobgsError, RuntimeError):
    """The native extension could not be compiled or loaded; carries the full log."""


def check_shape(name: str, value, shape: tuple) -> None:
    """Raise :class:`InputError` unless ``value.shape`` matches ``shape``.

    ``shape`` entries that are ``None`` match any size; a string entry names a size that
    must be equal wherever the same string appears (checked by the caller).
    """
    got = tuple(value.shape)
    if len(got) != len(shape) or any(
        s is not None and not isinstance(s, str) and g != s for g, s in zip(got, shape)
    ):
        want = "[" + ", ".join("*" if s is None else str(s) for s in shape) + "]"
        raise InputError(f"{name} must have shape {want}, got {list(got)}")
