"""Lazy re-exports for the library's subpackages: ``from cobgs.refine import refine`` imports
``cobgs.refine.alternation`` only when the name is first asked for (PEP 562), so importing a
subpackage stays cheap and the subpackages never import each other at load time."""

from __future__ import annotations

import importlib
from typing import Callable, Mapping


def lazy_getattr(package: str, where: Mapping[str, str], namespace: dict) -> Callable[[str], object]:
    """A module ``__getattr__`` serving ``name`` from ``package.<where[name]>`` (cached in
    ``namespace``, the package's globals)."""

    def __getattr__(name: str):
        mod = where.get(name)
        if mod is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{package}.{mod}"), name)
        namespace[name] = value
        return value

    return __getattr__
