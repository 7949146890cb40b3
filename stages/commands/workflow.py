"""``cobgs run | status | cache gc/ls/verify | stages``: the workflow commands.

The engine (``pipeline/``) implements them; this module only hands it the program's stage
registry (stages/registry.py) and version.
"""

from __future__ import annotations


def _registry():
    from stages.registry import load_registry

    return load_registry()


def _version() -> str:
    from cobgs import __version__

    return __version__


def register(sub) -> None:
    from pipeline.commands import register as register_commands

    register_commands(sub, _registry, _version)
